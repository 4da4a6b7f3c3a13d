"""``smdm demo``: sparse keyframes on real motion capture, with nothing to download.

1. **Keyframes.** Loads CMU motion capture from BVH files — ``--bvh PATH ...``, else the CMU clips
   Debian/Ubuntu's ``assimp-testmodels`` package installs under ``/usr/share/assimp/models/BVH/``
   (cgspeed's 2008 release), else ``../shared/data/cmu-mocap`` (or ``$SMDM_MOCAP``) — converts them
   to HumanML3D's 22 joints in metres at 20 fps and cuts them into windows of up to 196 frames
   (HumanML3D's longest motion). For every reduction rate it keeps the frames chosen by VW
   (Visvalingam–Whyatt), uniform spacing, random choice and MDO, interpolates all 22 joints
   linearly in between and reports the mean joint position error (mm) of that reconstruction.
   Selection features: the global joint positions (66-D, metres) plus ``frame index × 0.1 m``
   (``--frame-index-scale``; the time axis' weight in VW's triangle areas. On the assimp CMU clips
   VW beats uniform spacing at 0.1 m/frame but not at 0.01, so the table shows what it measures).
   A PNG shows one window: a joint trajectory with the VW keyframes marked and the VW / uniform
   reconstructions, and a stick-figure strip (original vs. VW reconstruction).
2. **Training.** Trains the in-package backbone (:class:`~smdm_plugin.backbone.TinyMDM` +
   :class:`~smdm_plugin.diffusion.SimpleDiffusion`) dense and sparse (80% reduction) on the same
   windows for ``--minutes`` in total, time-sliced (each step goes to the model that has used less
   time so far, so machine load hits both alike), and reports the measured speed ratio and both
   loss curves. HumanML3D's 263-D features need foot contacts and rotations that BVH positions do
   not give directly, so the demo trains on a simple representation computed from the joint
   positions (66-D per frame): joints 1..21 relative to the root (63), root height (1) and the
   root's planar velocity in x and z (2, metres per frame), normalised by the training-set mean /
   std. Unconditional (no text).

Prints the output folder at the end: ``keyframes.md`` / ``keyframes.csv``, ``keyframes.png``,
``training.md``, ``loss.png``, ``summary.json``.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

ASSIMP_BVH = "/usr/share/assimp/models/BVH"
METHODS = ("vw", "uniform", "random", "mdo")
NO_BVH = """smdm demo: no BVH motion capture found.
  Pass one or more files:      smdm demo --bvh path/to/clip.bvh
  or install CMU test clips:   sudo apt-get install assimp-testmodels
                               (puts CMU BVH files under /usr/share/assimp/models/BVH/)
  or download CMU clips in BVH form (cgspeed conversion of mocap.cs.cmu.edu) and pass them with --bvh,
  or set SMDM_MOCAP to a folder of CMU .bvh files."""

# the 22-joint skeleton (HumanML3D / SMPL order) as parent indices, for the stick figures
PARENTS22 = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)


# ----------------------------------------------------------------------------------------- data
def find_bvh(paths: Optional[Sequence[str]] = None) -> List[str]:
    """The BVH files to use: ``paths`` (files or folders), else the default locations."""
    if paths:
        out: List[str] = []
        for p in paths:
            out += sorted(glob.glob(os.path.join(p, "*.bvh"))) if os.path.isdir(p) else [p]
        return out
    for folder in (os.environ.get("SMDM_MOCAP"), ASSIMP_BVH, os.path.join("..", "shared", "data", "cmu-mocap"),
                   str(Path(__file__).resolve().parents[2] / "shared" / "data" / "cmu-mocap")):
        if folder and os.path.isdir(folder):
            files = sorted(glob.glob(os.path.join(folder, "*.bvh")))
            if files:
                return files
    return []


def load_clips(files: Sequence[str], fps: int = 20, max_clips: Optional[int] = None,
               log=print) -> List[Tuple[str, np.ndarray]]:
    """``[(name, joints [T, 22, 3] metres)]``; files that are not CMU skeletons are skipped with a
    note (the 22-joint mapping needs CMU's joint names; cgspeed 2008 and 2010 both work)."""
    from ..io.bvh import load_cmu_clip

    clips = []
    for f in files:
        try:
            j = load_cmu_clip(f, fps=fps)
        except Exception as e:  # not a CMU skeleton, malformed file...
            log(f"  skipping {f}: {str(e).splitlines()[0][:120]}")
            continue
        if len(j) < 20:
            log(f"  skipping {f}: only {len(j)} frames at {fps} fps")
            continue
        clips.append((Path(f).stem, j.astype(np.float32)))
        if max_clips and len(clips) >= max_clips:
            break
    return clips


def windows(clips: Sequence[Tuple[str, np.ndarray]], length: int = 196, min_len: int = 40,
            max_windows: Optional[int] = None) -> List[Tuple[str, int, np.ndarray]]:
    """Consecutive non-overlapping windows of up to ``length`` frames (the tail if >= min_len)."""
    out = []
    for name, j in clips:
        for s in range(0, len(j), length):
            w = j[s:s + length]
            if len(w) >= min_len:
                out.append((name, s, w))
            if max_windows and len(out) >= max_windows:
                return out
    return out


def selection_features(joints: np.ndarray, frame_index_scale: float = 0.1) -> np.ndarray:
    """``[T, 67]``: the 22 global joint positions (metres) + frame index × scale."""
    T = joints.shape[0]
    return np.concatenate([joints.reshape(T, -1), (np.arange(T) * frame_index_scale)[:, None]], 1)


def reconstruction_error(joints: np.ndarray, mask: np.ndarray) -> Tuple[float, np.ndarray]:
    """Mean joint position error (mm) over all frames of linear interpolation from the keyframes
    ``mask [T]``, and the reconstruction ``[T, 22, 3]``."""
    from ..core.interpolation import interpolate_keyframes

    T = joints.shape[0]
    x = torch.from_numpy(joints.reshape(1, T, -1)).double()
    rec = interpolate_keyframes(x, torch.from_numpy(mask).view(1, T)).reshape(T, -1, 3).numpy()
    err = np.linalg.norm(rec - joints, axis=-1).mean() * 1000.0
    return float(err), rec


def keyframe_study(wins, reductions: Sequence[float], methods: Sequence[str] = METHODS, seed: int = 0,
                   frame_index_scale: float = 0.1) -> Dict[str, Any]:
    """Reconstruction error (mm) per method and reduction, averaged over the windows."""
    from ..core.selection import select_keyframes

    g = torch.Generator().manual_seed(seed)
    table: Dict[str, Dict[float, float]] = {m: {} for m in methods}
    for r in reductions:
        for m in methods:
            errs = []
            for _, _, w in wins:
                f = torch.from_numpy(selection_features(w, frame_index_scale)).float()[None]
                mask = select_keyframes(f, None, r, m, generator=g)[0].numpy()
                errs.append(reconstruction_error(w, mask)[0])
            table[m][r] = float(np.mean(errs))
    return {"reductions": list(reductions), "methods": list(methods), "mpjpe_mm": table,
            "frame_index_scale": frame_index_scale,
            "windows": len(wins), "frames": int(sum(len(w) for _, _, w in wins))}


def keyframe_markdown(study: Dict[str, Any]) -> str:
    reds = study["reductions"]
    lines = [f"Mean joint position error (mm) of linear interpolation from the keyframes, "
             f"{study['windows']} windows, {study['frames']} frames at 20 fps (selection features: "
             f"global joint positions + frame index × {study.get('frame_index_scale', 0.1)} m)",
             "", "| method | " + " | ".join(f"{int(round(r * 100))}% dropped" for r in reds) + " |",
             "| --- |" + " ---: |" * len(reds)]
    for m in study["methods"]:
        lines.append(f"| {m} | " + " | ".join(f"{study['mpjpe_mm'][m][r]:.1f}" for r in reds) + " |")
    return "\n".join(lines)


def plot_keyframes(win: np.ndarray, title: str, reduction: float, path: str, joint: int = 21,
                   frame_index_scale: float = 0.1) -> None:
    """Trajectory of ``joint`` (default: right wrist) with VW keyframes and reconstructions, and
    a stick-figure strip of the original vs. the VW reconstruction."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..core.selection import select_keyframes

    T = len(win)
    f = torch.from_numpy(selection_features(win, frame_index_scale)).float()[None]
    vw = select_keyframes(f, None, reduction, "vw")[0].numpy()
    uni = select_keyframes(f, None, reduction, "uniform")[0].numpy()
    e_vw, rec_vw = reconstruction_error(win, vw)
    e_uni, rec_uni = reconstruction_error(win, uni)
    fig = plt.figure(figsize=(13, 7.5))
    t = np.arange(T) / 20.0
    for i, (axis, lab) in enumerate(((1, "height (y)"), (0, "x"))):
        ax = fig.add_subplot(2, 2, i + 1)
        ax.plot(t, win[:, joint, axis], color="0.2", lw=2, label="motion capture")
        ax.plot(t, rec_vw[:, joint, axis], color="tab:red", lw=1.2, label=f"VW interpolation ({e_vw:.0f} mm)")
        ax.plot(t, rec_uni[:, joint, axis], color="tab:blue", lw=1.0, ls="--",
                label=f"uniform interpolation ({e_uni:.0f} mm)")
        ax.scatter(t[vw], win[vw, joint, axis], color="tab:red", s=22, zorder=3, label="VW keyframes")
        ax.set_xlabel("time (s)")
        ax.set_ylabel(f"right wrist {lab} (m)")
        if i == 0:
            ax.legend(fontsize=8)
    ax = fig.add_subplot(2, 1, 2)
    n = 10
    frames = np.linspace(0, T - 1, n).round().astype(int)
    spread = 0.9
    for k, fr in enumerate(frames):
        for src, col, lw in ((win, "0.3", 2.2), (rec_vw, "tab:red", 1.0)):
            p = src[fr] - np.array([src[fr, 0, 0], 0, src[fr, 0, 2]]) + np.array([k * spread, 0, 0])
            for j, par in enumerate(PARENTS22):
                if par >= 0:
                    ax.plot([p[j, 0], p[par, 0]], [p[j, 1], p[par, 1]], color=col, lw=lw)
        ax.text(k * spread, -0.1, f"{fr}{'*' if vw[fr] else ''}", ha="center", fontsize=8)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title("stick figures (x-y view, root-centred): grey = motion capture, red = VW reconstruction; "
                 "* = keyframe", fontsize=9)
    fig.suptitle(f"{title}: {T} frames, {int(vw.sum())} VW keyframes ({int(round(reduction * 100))}% dropped)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------------------- training
def motion_features(joints: np.ndarray) -> np.ndarray:
    """The demo's training representation ``[T, 66]`` from joints ``[T, 22, 3]`` (metres):
    joints 1..21 minus the root (63), root height (1), root planar velocity x, z (2, m/frame;
    the last frame repeats the previous velocity)."""
    T = joints.shape[0]
    root = joints[:, 0]
    rel = (joints[:, 1:] - root[:, None]).reshape(T, 63)
    vel = np.diff(root[:, [0, 2]], axis=0)
    vel = np.concatenate([vel, vel[-1:]], 0) if T > 1 else np.zeros((T, 2))
    return np.concatenate([rel, root[:, 1:2], vel], 1).astype(np.float32)


def training_set(clips, length: int, stride: int) -> np.ndarray:
    """All crops of ``length`` frames (every ``stride`` frames) as ``[M, length, 66]``."""
    crops = []
    for _, j in clips:
        feats = motion_features(j)
        for s in range(0, max(1, len(feats) - length + 1), stride):
            c = feats[s:s + length]
            if len(c) == length:
                crops.append(c)
    if not crops:
        raise ValueError(f"smdm demo: no clip has {length} frames; use --frames with a smaller value")
    return np.stack(crops)


def train_dense_vs_sparse(data: np.ndarray, seconds: float, batch: int = 32, reduction: float = 0.8,
                          latent: int = 256, layers: int = 4, device: str = "cpu", seed: int = 0,
                          max_steps: Optional[int] = None, progress: bool = True) -> Dict[str, Any]:
    """Train dense and sparse copies of the same TinyMDM, time-sliced, for ``seconds`` in total."""
    from ..adapters.mdm import sparsify
    from ..reference.backbone import TinyMDM
    from ..core.config import SparseConfig
    from ..reference.diffusion import SimpleDiffusion

    dev = torch.device(device)
    mean, std = data.reshape(-1, data.shape[-1]).mean(0), data.reshape(-1, data.shape[-1]).std(0) + 1e-4
    x_all = torch.from_numpy((data - mean) / std).float()  # [M, N, D]
    M, N, D = x_all.shape
    runs = {}
    for name in ("dense", "sparse"):
        torch.manual_seed(seed)
        model = TinyMDM(njoints=D, nfeats=1, latent_dim=latent, ff_size=2 * latent, num_layers=layers,
                        num_heads=4, cond_mode="no_cond", dropout=0.1).to(dev)
        diffusion = SimpleDiffusion(100)
        if name == "sparse":
            sparsify(model, SparseConfig(reduction=reduction, feature="raw"), diffusion=diffusion)
        runs[name] = {"model": model.train(), "diffusion": diffusion, "spent": 0.0, "steps": 0,
                      "loss": [], "time": [], "opt": torch.optim.AdamW(model.parameters(), lr=2e-4),
                      "gen": torch.Generator().manual_seed(seed)}
    for r in runs.values():  # one untimed warm-up step each (allocations, lazy optimiser state)
        x = x_all[:batch].permute(0, 2, 1).unsqueeze(2).to(dev)
        mask = torch.ones(x.shape[0], 1, 1, N, dtype=torch.bool, device=dev)
        t = torch.zeros(x.shape[0], dtype=torch.long, device=dev)
        r["diffusion"].training_losses(r["model"], x, t, {"y": {"mask": mask}})["loss"].mean().backward()
        r["model"].zero_grad(set_to_none=True)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=round(seconds), desc="training dense + sparse (s)", mininterval=0.5,
                   bar_format="{l_bar}{bar}| {n:.0f}/{total_fmt} s{postfix}")
    mask = torch.ones(batch, 1, 1, N, dtype=torch.bool, device=dev)
    while True:
        live = [k for k, v in runs.items() if v["spent"] < seconds / 2 and not (max_steps and v["steps"] >= max_steps)]
        if not live:
            break
        name = min(live, key=lambda k: runs[k]["spent"])
        r = runs[name]
        idx = torch.randint(0, M, (batch,), generator=r["gen"])  # same data order for both
        t = torch.randint(0, r["diffusion"].num_timesteps, (batch,), generator=r["gen"]).to(dev)
        x = x_all[idx].permute(0, 2, 1).unsqueeze(2).to(dev)
        t0 = time.perf_counter()
        loss = r["diffusion"].training_losses(r["model"], x, t, {"y": {"mask": mask}})["loss"].mean()
        r["opt"].zero_grad(set_to_none=True)
        loss.backward()
        r["opt"].step()
        dt = time.perf_counter() - t0
        r["spent"] += dt
        r["steps"] += 1
        r["loss"].append(loss.item())
        r["time"].append(r["spent"])
        if bar is not None:
            total = min(seconds, runs["dense"]["spent"] + runs["sparse"]["spent"])
            bar.set_postfix_str(", ".join(f"{k} {v['steps']} steps loss {np.mean(v['loss'][-10:]):.3f}"
                                          for k, v in runs.items() if v["loss"]), refresh=False)
            bar.update(total - bar.n)  # refreshes at most every mininterval
    if bar is not None:
        bar.close()
    out: Dict[str, Any] = {"frames": N, "batch": batch, "reduction": reduction, "latent": latent,
                           "layers": layers, "crops": M}
    for name, r in runs.items():
        k = max(1, len(r["loss"]) // 10)
        out[name] = {"steps": r["steps"], "seconds": r["spent"],
                     "steps_per_s": r["steps"] / max(r["spent"], 1e-9),
                     "final_loss": float(np.mean(r["loss"][-k:])) if r["loss"] else None,
                     "loss": r["loss"], "time": r["time"]}
    out["speed_ratio"] = out["sparse"]["steps_per_s"] / max(out["dense"]["steps_per_s"], 1e-9)
    return out


def plot_losses(train: Dict[str, Any], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    for name, col in (("dense", "tab:blue"), ("sparse", "tab:red")):
        r = train[name]
        if not r["loss"]:
            continue
        loss = np.asarray(r["loss"])
        k = max(1, len(loss) // 25)
        smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
        lab = f"{name} ({r['steps_per_s']:.2f} steps/s)"
        axes[0].plot(np.arange(len(smooth)) + k, smooth, color=col, label=lab)
        axes[1].plot(np.asarray(r["time"])[k - 1:], smooth, color=col, label=lab)
    axes[0].set_xlabel("training step")
    axes[1].set_xlabel("training time (s)")
    for ax in axes:
        ax.set_ylabel("diffusion loss (x0 MSE, normalised)")
        ax.set_yscale("log")
        ax.legend()
    fig.suptitle(f"dense vs sparse ({int(round(train['reduction'] * 100))}% of frames dropped): "
                 f"sparse runs {train['speed_ratio']:.2f}x the steps per second")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--bvh", nargs="+", default=None, help="BVH files or folders (default: see above)")
    p.add_argument("--out", default=os.path.join("smdm_out", "demo"), help="output folder")
    p.add_argument("--minutes", type=float, default=2.0, help="training time, dense + sparse together")
    p.add_argument("--reductions", nargs="+", type=float, default=[0.6, 0.7, 0.8, 0.9])
    p.add_argument("--train-reduction", type=float, default=0.8)
    p.add_argument("--frames", type=int, default=120, help="training crop length (frames at 20 fps)")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--latent", type=int, default=256)
    p.add_argument("--layers", type=int, default=4)
    p.add_argument("--device", default="auto")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-clips", type=int, default=None)
    p.add_argument("--frame-index-scale", type=float, default=0.1,
                   help="metres per frame appended to the joint positions for keyframe selection")
    p.add_argument("--threads", type=int, default=None,
                   help="torch.set_num_threads (1 is faster on a CPU shared with other jobs)")
    p.add_argument("--quick", action="store_true", help="a smoke run: 1 clip, 2 windows, a few steps")


def main_demo(args: argparse.Namespace) -> int:
    from .bench import pick_device

    t_start = time.perf_counter()
    if args.threads:
        torch.set_num_threads(args.threads)
    files = find_bvh(args.bvh)
    if not files:
        print(NO_BVH, file=sys.stderr)
        return 2
    if args.quick:
        args.max_clips = 1
        args.reductions = [0.8]
        args.frames, args.batch, args.latent, args.layers = min(args.frames, 60), 4, 32, 1
    print(f"smdm demo: reading {len(files)} BVH file(s) from {os.path.dirname(os.path.abspath(files[0]))}")
    clips = load_clips(files, max_clips=args.max_clips)
    if not clips:
        print("smdm demo: none of the BVH files is a CMU skeleton this demo can map to 22 joints.\n" + NO_BVH,
              file=sys.stderr)
        return 2
    os.makedirs(args.out, exist_ok=True)
    print(f"  {len(clips)} clip(s): " + ", ".join(f"{n} ({len(j)} frames)" for n, j in clips))

    # 1. keyframes
    wins = windows(clips, 196, max_windows=2 if args.quick else None)
    study = keyframe_study(wins, args.reductions, seed=args.seed, frame_index_scale=args.frame_index_scale)
    table = keyframe_markdown(study)
    print("\n## Keyframes vs. reconstruction error\n\n" + table)
    with open(os.path.join(args.out, "keyframes.md"), "w") as f:
        f.write(table + "\n")
    with open(os.path.join(args.out, "keyframes.csv"), "w") as f:
        f.write("method," + ",".join(str(r) for r in study["reductions"]) + "\n")
        for m in study["methods"]:
            f.write(m + "," + ",".join(f"{study['mpjpe_mm'][m][r]:.3f}" for r in study["reductions"]) + "\n")
    name, start, win = wins[0]
    red_plot = 0.8 if 0.8 in args.reductions else args.reductions[0]
    plot_keyframes(win, f"{name} frames {start}-{start + len(win) - 1}", red_plot,
                   os.path.join(args.out, "keyframes.png"), frame_index_scale=args.frame_index_scale)

    # 2. training
    dev = pick_device(args.device)
    data = training_set(clips, args.frames, stride=max(1, args.frames // 4))
    seconds = 60.0 * args.minutes
    print(f"\n## Training dense vs. sparse ({int(round(args.train_reduction * 100))}% dropped) for "
          f"{seconds:.0f} s in total on {dev}: {len(data)} crops of {args.frames} frames, 66-D features")
    train = train_dense_vs_sparse(data, seconds, args.batch, args.train_reduction, args.latent, args.layers,
                                  str(dev), args.seed, max_steps=3 if args.quick else None,
                                  progress=not args.quick)
    plot_losses(train, os.path.join(args.out, "loss.png"))
    lines = ["| model | steps | seconds | steps/s | final loss |", "| --- | ---: | ---: | ---: | ---: |"]
    for n in ("dense", "sparse"):
        r = train[n]
        fl = "—" if r["final_loss"] is None else f"{r['final_loss']:.4f}"
        lines.append(f"| {n} | {r['steps']} | {r['seconds']:.1f} | {r['steps_per_s']:.2f} | {fl} |")
    lines.append(f"\nsparse / dense training speed: **{train['speed_ratio']:.2f}×** (TinyMDM latent "
                 f"{args.latent}, {args.layers} layers, batch {args.batch}, {args.frames} frames)")
    ttable = "\n".join(lines)
    print(ttable)
    with open(os.path.join(args.out, "training.md"), "w") as f:
        f.write(ttable + "\n")
    summary = {"files": files, "clips": [[n, len(j)] for n, j in clips], "keyframes": study,
               "training": {k: v for k, v in train.items()}, "seconds": time.perf_counter() - t_start}
    summary["keyframes"]["mpjpe_mm"] = {m: {str(r): v for r, v in d.items()}
                                        for m, d in study["mpjpe_mm"].items()}
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    print(f"\noutputs: {os.path.abspath(args.out)}")
    return 0


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="smdm demo", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    return main_demo(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
