"""``smdm render``: a saved motion as an animated GIF of the skeleton (no ffmpeg needed).

    smdm render motion.npy                          # -> motion.gif
    smdm render a.npy b.npy --titles dense sparse --keyframes 0 30 60 --out ab.gif
    smdm render clip.bvh --stride 2                 # every 2nd frame, same speed
    smdm render save/x/results.npy --allow-pickle --sample 1   # MDM's sample.generate output

Motions given together are drawn side by side with one camera scale; ``--keyframes`` frames are
highlighted in red (figure, timeline tick, ghost poses of the keyframes around the current frame).
"""
from __future__ import annotations

import argparse
import os
import sys
from typing import List, Optional

from .common.args import (add_common_flags, add_overwrite, existing_path, float_range, int_range, note_printer,
                          output_path, positional_type, progress_of)
from .common.motion_files import ACCEPTED, add_motion_file_options


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="smdm render", description=__doc__.split("\n\n")[0],
                                epilog=f"accepted inputs: {ACCEPTED}")
    p.add_argument("motions", nargs="+", metavar="MOTION", help=".npy or .bvh file(s), drawn side by side")
    p.add_argument("--out", default=None, type=output_path("file"),
                   help="GIF path (default: the first input's name with .gif, here)")
    p.add_argument("--keyframes", nargs="+", type=int_range(0), default=(), metavar="FRAME",
                   help="frames to highlight (0-based)")
    p.add_argument("--titles", nargs="+", default=None, help="one title per motion (default: file names)")
    p.add_argument("--fps", type=float_range(0, lo_open=True, hi=1000), default=20.0,
                   help="frames per second of .npy motions, and the rate BVH files are resampled to (default 20)")
    p.add_argument("--stride", type=int_range(1), default=1, help="draw every STRIDE-th frame, same speed (default 1)")
    add_motion_file_options(p)
    p.add_argument("--size", type=float_range(1, 20), default=3.0, help="panel size in inches at 80 dpi (default 3)")
    add_common_flags(p, device=None, threads=False, why_not="it draws with matplotlib on the CPU, no torch")
    add_overwrite(p)
    return p


def main(argv: Optional[List[str]] = None) -> int:
    from ..io.files import OutputExistsError
    from .common.animation import Panel, render_gif
    from .common.motion_files import load_motion, rate_differs

    p = build_parser()
    a = p.parse_args(argv)
    positional_type(p, a, "motions", existing_path("file"), "MOTION")
    if a.titles is not None and len(a.titles) != len(a.motions):
        p.error(f"--titles: give one title per motion ({len(a.motions)}), got {len(a.titles)}")
    out = a.out or os.path.splitext(os.path.basename(a.motions[0]))[0] + ".gif"
    if not out.lower().endswith(".gif"):
        p.error(f"--out must end in .gif, got {out!r}")
    from ..io.outdir import check_no_overlap

    try:
        check_no_overlap(out, {f"motion {m}": m for m in a.motions})
    except OutputExistsError as e:
        p.error(str(e))
    if os.path.exists(out) and not a.overwrite:
        p.error(f"--out {out!r} exists; pass --overwrite to replace it")
    panels, rates = [], []
    for k, path in enumerate(a.motions):
        try:
            m = load_motion(path, fps=a.fps, sample=a.sample, allow_pickle=a.allow_pickle)
        except (OSError, ValueError) as e:
            p.error(str(e).splitlines()[0])
        differs = rate_differs(m, a.fps)
        if differs:  # drawn at the rate it has (it plays at its real speed), said
            print(f"smdm render: warning: {differs}; drawn at {m.fps:g} fps", file=sys.stderr)
        bad = [f for f in a.keyframes if f >= len(m.joints)]
        if bad:
            p.error(f"--keyframes {bad} beyond the {len(m.joints)} frames of {path}")
        title = a.titles[k] if a.titles else os.path.basename(path)
        panels.append(Panel(m.joints, title, a.keyframes, chains=m.chains))
        rates.append(m.fps)
        note_printer(a)(f"{path}: {len(m.joints)} frames, {m.joints.shape[1]} joints ({m.kind})")
    try:
        render_gif(panels, out, fps=rates[0], stride=a.stride, panel_size=a.size,
                   overwrite=a.overwrite, progress=progress_of(a))
    except OutputExistsError as e:
        p.error(str(e))
    frames = len(range(0, max(len(q.joints) for q in panels), a.stride))
    print(f"wrote {out} ({frames} frames)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
