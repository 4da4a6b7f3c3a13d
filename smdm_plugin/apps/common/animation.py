"""Skeleton animations as GIF (matplotlib's Pillow writer; no ffmpeg): one or more motions side by
side, keyframes highlighted.

Each panel shows a stick figure seen from a fixed oblique camera that follows the root over a floor
grid, the root's path so far, the keyframe poses as faint ghosts where they stand, and a timeline with
a tick per keyframe. On a keyframe frame the whole figure is drawn in :data:`HIGHLIGHT` (pure red,
used for nothing else, so a test or a viewer can find keyframe frames by colour).

Units are whatever the joints are in (HumanML3D: metres, y up); the view is scaled to the body.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import List, Optional, Sequence

import numpy as np

#: the colour of the figure on keyframe frames (and of nothing else)
HIGHLIGHT = "#ff0000"
GHOST = "#f4a582"
CHAIN_COLOURS = ("#1f77b4", "#2ca02c", "#444444", "#9467bd", "#17becf")

#: kinematic chains (joint indices from the root outwards), as MDM's ``paramUtil``
CHAINS = {
    22: ((0, 2, 5, 8, 11), (0, 1, 4, 7, 10), (0, 3, 6, 9, 12, 15), (9, 14, 17, 19, 21), (9, 13, 16, 18, 20)),
    21: ((0, 11, 12, 13, 14, 15), (0, 16, 17, 18, 19, 20), (0, 1, 2, 3, 4), (3, 5, 6, 7), (3, 8, 9, 10)),
}


def chains_from_parents(parents: Sequence[int]) -> tuple:
    """Kinematic chains (one per leaf, cut where a branch starts) from a parent list (-1 = root)."""
    children = {j: [c for c, p in enumerate(parents) if p == j] for j in range(len(parents))}
    chains, stack = [], [(j, (j,)) for j, p in enumerate(parents) if p < 0]
    while stack:
        j, chain = stack.pop()
        kids = children[j]
        if not kids:
            chains.append(chain)
            continue
        stack.append((kids[0], chain + (kids[0],)))
        stack += [(k, (j, k)) for k in kids[1:]]
    return tuple(c for c in chains if len(c) > 1)


@dataclass
class Panel:
    """One motion to draw: ``joints [N, J, 3]`` (y up), a title, the keyframe frames to highlight,
    and its kinematic chains (default: HumanML3D's 22 / KIT's 21 joints by ``J``)."""

    joints: np.ndarray
    title: str = ""
    keyframes: Sequence[int] = ()
    chains: Optional[tuple] = None
    colours: Sequence[str] = field(default_factory=lambda: CHAIN_COLOURS)

    def __post_init__(self) -> None:
        j = np.asarray(self.joints, dtype=np.float64)
        if j.ndim != 3 or j.shape[-1] != 3 or j.shape[0] < 1:
            raise ValueError(f"Panel: joints must be [N, J, 3], got {j.shape}")
        if not np.isfinite(j).all():
            raise ValueError(f"Panel {self.title!r}: joints hold NaN or inf")
        self.joints = j
        if self.chains is None:
            if j.shape[1] not in CHAINS:
                raise ValueError(f"Panel: no skeleton known for J={j.shape[1]} joints (22: HumanML3D, 21: KIT); "
                                 "pass chains")
            self.chains = CHAINS[j.shape[1]]
        kf = sorted({int(k) for k in self.keyframes})
        if kf and (kf[0] < 0 or kf[-1] >= j.shape[0]):
            raise ValueError(f"Panel {self.title!r}: keyframes must be in [0, {j.shape[0]}), got {kf}")
        self.keyframes = kf


def _nice(x: float) -> float:
    """The largest of 1, 2, 5 x 10^k that is <= ``x`` (grid spacing)."""
    k = 10.0 ** math.floor(math.log10(x))
    return k * (5 if x / k >= 5 else 2 if x / k >= 2 else 1)


class _Camera:
    """Orthographic camera: rotation ``azim`` about the up axis, tilt ``elev``; follows the root."""

    def __init__(self, azim: float, elev: float) -> None:
        a, e = math.radians(azim), math.radians(elev)
        self.ca, self.sa, self.ce, self.se = math.cos(a), math.sin(a), math.cos(e), math.sin(e)

    def project(self, p: np.ndarray, centre: np.ndarray) -> np.ndarray:
        """``[..., 3]`` world (y up) -> ``[..., 2]`` screen, relative to ``centre [3]``."""
        d = p - centre
        x = self.ca * d[..., 0] - self.sa * d[..., 2]
        depth = self.sa * d[..., 0] + self.ca * d[..., 2]
        return np.stack([x, d[..., 1] * self.ce - depth * self.se], -1)


def _segments(parts: Sequence[np.ndarray]) -> np.ndarray:
    """Polylines ``[n_i, 2]`` joined into one ``[M, 2]`` array with NaN rows between them (one artist)."""
    out: List[np.ndarray] = []
    for part in parts:
        out += [part, np.full((1, 2), np.nan)]
    return np.concatenate(out, 0) if out else np.zeros((0, 2))


class _PanelArtist:
    """The matplotlib artists of one panel and their per-frame update. ``reach`` (the largest
    joint-to-root distance of all panels) sets the common scale and the grid spacing."""

    def __init__(self, fig, rect, panel: Panel, camera: _Camera, frames: int, reach: float) -> None:
        self.p, self.cam = panel, camera
        j = panel.joints
        self.floor = float(j[..., 1].min())
        self.grid_step = _nice(reach / 2)
        ax = fig.add_axes([rect[0], rect[1] + 0.1 * rect[3], rect[2], 0.82 * rect[3]])
        half = 1.25 * reach
        ax.set_xlim(-half, half)
        ax.set_ylim(-0.4 * half, 1.45 * half)
        ax.set_aspect("equal")
        ax.axis("off")
        self.n_grid = 2 * int(math.ceil(1.5 * half / self.grid_step)) + 1
        self.grid = ax.plot([], [], color="#dddddd", lw=0.6, zorder=0)[0]
        self.trail = ax.plot([], [], color="#aaaaaa", lw=1.0, zorder=1)[0]
        self.ghost = ax.plot([], [], color=GHOST, lw=1.0, zorder=2)[0]
        colours = list(panel.colours)
        self.colours = [colours[i % len(colours)] for i in range(len(panel.chains))]
        self.bones = [ax.plot([], [], color=c, lw=2.2, solid_capstyle="round", zorder=3)[0] for c in self.colours]
        fig.text(rect[0] + rect[2] / 2, rect[1] + 0.95 * rect[3], panel.title, ha="center", va="center", fontsize=9)
        self.label = ax.text(0.02, 0.02, "", transform=ax.transAxes, fontsize=7, color="#444444")
        self.kf_label = ax.text(0.98, 0.02, "", transform=ax.transAxes, fontsize=7, ha="right",
                                color=HIGHLIGHT, fontweight="bold")
        tl = fig.add_axes([rect[0] + 0.08 * rect[2], rect[1] + 0.04 * rect[3], 0.84 * rect[2], 0.04 * rect[3]])
        tl.set_xlim(-0.5, max(frames - 0.5, 0.5))
        tl.set_ylim(-1, 1)
        tl.axis("off")
        tl.plot([0, max(len(j) - 1, 0)], [0, 0], color="#bbbbbb", lw=2, solid_capstyle="butt")
        for k in panel.keyframes:
            tl.plot([k, k], [-0.9, 0.9], color="#333333", lw=1.2)
        self.cursor = tl.plot([0], [0], marker="o", ms=5, color="#1f77b4")[0]
        self.keys = np.asarray(panel.keyframes, dtype=int)

    def update(self, i: int) -> None:
        j, chains = self.p.joints, self.p.chains
        n = min(i, len(j) - 1)
        root = j[n, 0]
        centre = np.array([root[0], self.floor, root[2]])

        def proj(pts: np.ndarray) -> np.ndarray:
            return self.cam.project(pts, centre)

        # floor grid around the root, snapped to world coordinates so that it scrolls with the root
        s, m = self.grid_step, self.n_grid // 2
        gx, gz = math.floor(root[0] / s) * s, math.floor(root[2] / s) * s
        k = np.arange(-m, m + 1) * s
        ends = np.array([-m * s, m * s])
        along_z = np.stack(np.broadcast_arrays(gx + k[:, None], self.floor, gz + ends[None]), -1)  # [L, 2, 3]
        along_x = np.stack(np.broadcast_arrays(gx + ends[None], self.floor, gz + k[:, None]), -1)
        self.grid.set_data(*_segments(list(proj(np.concatenate([along_z, along_x], 0)))).T)
        path = j[: n + 1, 0].copy()
        path[:, 1] = self.floor
        self.trail.set_data(*proj(path).T)
        # ghosts of the keyframes around the current frame: where the motion comes from and goes to
        around = [k for k in (self.keys[self.keys < n][-1:].tolist() + self.keys[self.keys > n][:1].tolist())]
        self.ghost.set_data(*_segments([proj(j[k])[list(c)] for k in around for c in chains]).T)
        q = proj(j[n])
        key = i == n and n in self.keys
        for line, chain, colour in zip(self.bones, chains, self.colours):
            line.set_data(q[list(chain), 0], q[list(chain), 1])
            line.set_color(HIGHLIGHT if key else colour)
            line.set_linewidth(3.2 if key else 2.2)
        self.label.set_text(f"frame {n}/{len(j) - 1}")  # 0-based, like every other frame number
        self.kf_label.set_text("keyframe" if key else "")
        self.cursor.set_data([n], [0])


def render_gif(panels: Sequence[Panel], path: str, fps: float = 20.0, stride: int = 1, azim: float = -35.0,
               elev: float = 20.0, panel_size: float = 3.0, dpi: int = 80, overwrite: bool = False,
               progress: bool = True, suptitle: str = "") -> str:
    """Write ``panels`` side by side as an animated GIF at ``path`` (atomically; an existing file
    only with ``overwrite``). One GIF frame per ``stride`` motion frames of the longest panel
    (shorter ones hold their last frame), played at ``fps / stride`` frames per second so the
    motion keeps its speed. Returns ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import PillowWriter

    from ...io.files import check_new_file

    if not panels:
        raise ValueError("render_gif: no panel to draw")
    if not (fps > 0 and math.isfinite(fps)) or int(stride) < 1:
        raise ValueError(f"render_gif: fps must be > 0 and stride >= 1, got fps={fps}, stride={stride}")
    if not str(path).lower().endswith(".gif"):
        raise ValueError(f"render_gif: path must end in .gif, got {path!r}")
    check_new_file(path, overwrite, what="animation")
    frames = max(len(p.joints) for p in panels)
    shown = list(range(0, frames, int(stride)))
    cam = _Camera(azim, elev)
    top = 0.1 if suptitle else 0.0
    fig = plt.figure(figsize=(panel_size * len(panels), panel_size * 1.1 / (1 - top)), dpi=dpi)
    if suptitle:
        fig.suptitle(suptitle, fontsize=9)
    w = 1.0 / len(panels)
    reach = max(float(np.linalg.norm(p.joints - p.joints[:, :1], axis=-1).max()) for p in panels) or 1.0
    artists = [_PanelArtist(fig, (k * w, 0.0, w, 1.0 - top), p, cam, frames, reach) for k, p in enumerate(panels)]

    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    tmp = os.path.join(folder, f".{os.path.basename(path)}.{os.getpid()}.tmp.gif")
    writer = PillowWriter(fps=fps / int(stride))
    steps = range(len(shown))
    from ...support.progress import bars_on  # stderr a terminal (or --progress)

    if bars_on(progress):
        from tqdm.auto import tqdm

        steps = tqdm(steps, desc=f"rendering {os.path.basename(path)}", unit="frame", mininterval=0.5)
    try:
        with writer.saving(fig, tmp, dpi):
            for i in steps:
                for a in artists:
                    a.update(shown[i])
                writer.grab_frame()
        os.replace(tmp, path)
    except (OSError, RuntimeError) as e:
        from ...support.atomic import write_error

        named = write_error(e, path)  # a failed write (a full disk): one OSError naming the GIF
        if named is None and isinstance(e, OSError) and e.filename == tmp:
            named = OSError(e.errno, e.strerror, path)
        if named is None:
            raise
        raise named from None
    finally:
        plt.close(fig)
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
