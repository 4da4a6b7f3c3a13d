"""``smdm keyframes``: keyframe reconstruction error of BVH clips per selection method and rate.

Reads the clips as ``smdm demo`` does (CMU skeletons, 22 joints in metres at 20 fps, windows of
up to 196 frames), keeps the frames each method picks (VW, uniform, random, MDO) at every
reduction rate, interpolates the joints linearly in between and prints the mean joint position
error (mm) as a markdown table; ``--plot`` draws the first window. Files that cannot be used are
named with the reason, and so are the tolerances applied while reading them.
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings
from typing import List, Optional

from ..io.files import OutputExistsError, check_new_file
from ..core.config import SparseConfig
from .common.args import (add_common_flags, add_overwrite, existing_path, float_range, note_printer, output_path,
                          positional_type)

#: the library's default (docs/defaults.md), as in smdm demo
FRAME_INDEX_SCALE: float = SparseConfig.frame_index_scale

PLOT_FORMATS = (".png", ".pdf", ".svg", ".jpg", ".jpeg")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="smdm keyframes", description=__doc__.split("\n\n")[0])
    p.add_argument("bvh", nargs="*",   # checked after parsing (positional_type)
                   help="BVH files or folders (default: as smdm demo: the .bvh files of $SMDM_MOCAP when set, "
                        "else the 17 CMU clips embedded in the package)")
    p.add_argument("--reductions", nargs="+", type=float_range(0.0, 1.0, hi_open=True), default=[0.6, 0.7, 0.8, 0.9],
                   metavar="R", help="fractions of frames dropped, each in [0, 1) (default 0.6 0.7 0.8 0.9)")
    p.add_argument("--frame-index-scale", type=float_range(0.0, 100.0), default=FRAME_INDEX_SCALE, metavar="M",
                   help="metres per frame appended to the joint positions for selection (0-100; default "
                        f"{FRAME_INDEX_SCALE}, the library's SparseConfig default)")
    p.add_argument("--plot", default=None, metavar="FILE", type=output_path("file"),
                   help=f"write the keyframe figure of the first window here ({', '.join(PLOT_FORMATS)})")
    add_overwrite(p)
    add_common_flags(p, device=None, progress=False, why_not="it selects keyframes on the CPU and shows no progress")
    return p


def main(argv: Optional[List[str]] = None) -> int:
    p = build_parser()
    a = p.parse_args(argv)
    positional_type(p, a, "bvh", existing_path("any"))
    if a.plot is not None:
        if not a.plot.lower().endswith(PLOT_FORMATS):
            p.error(f"argument --plot: expected a file name ending in {', '.join(PLOT_FORMATS)}, got {a.plot!r}")
        try:
            from ..io.outdir import check_no_overlap

            check_no_overlap(a.plot, {f"input {b}": b for b in a.bvh}, what="--plot")
            check_new_file(a.plot, a.overwrite, what="--plot")
        except OutputExistsError as e:
            p.error(str(e))
        folder = os.path.dirname(os.path.abspath(a.plot))
        if not os.path.isdir(folder):
            p.error(f"argument --plot: the folder {folder!r} does not exist")
    from .common import keyframe_study as ks  # torch, numpy: after the arguments are checked
    from .common.threads import apply_threads

    apply_threads(a.threads)
    say = note_printer(a)

    if a.bvh and not ks.find_bvh(a.bvh):
        print(f"smdm keyframes: no .bvh file in {', '.join(a.bvh)}", file=sys.stderr)
        return 2
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:  # as smdm demo: the given BVH files, else $SMDM_MOCAP, else the embedded CMU clips
            source, _, clips = ks.motion_source(a.bvh or None, log=lambda m: print(m, file=sys.stderr))
        except ValueError as e:
            print(f"smdm keyframes: error: {e}", file=sys.stderr)
            return 2
    for w in caught:  # tolerances applied while reading (e.g. one motion row too many)
        print(f"  note: {w.message}", file=sys.stderr)
    if not clips:
        where = "given" if a.bvh else f"of {source}"
        print(f"smdm keyframes: error: none of the BVH files {where} could be used (the reason for each is above: a "
              "readable CMU-skeleton clip of 20 frames or more at 20 fps is needed); give no file to use the embedded "
              "CMU clips", file=sys.stderr)
        return 2
    say(f"smdm keyframes: motion from {source}", file=sys.stderr)
    wins = ks.windows(clips, 196)
    try:
        ks.require_windows(wins, clips)
    except ValueError as e:
        print(f"smdm keyframes: error: {e}", file=sys.stderr)
        return 2
    print(ks.keyframe_markdown(ks.keyframe_study(wins, a.reductions, frame_index_scale=a.frame_index_scale)))
    if a.plot:
        name, start, w = wins[0]
        # written atomically (a temporary file beside the target, then renamed): never a half-written figure
        ks.plot_keyframes(w, f"{name} frames {start}-{start + len(w) - 1}", 0.8, a.plot,
                          frame_index_scale=a.frame_index_scale)
        say(f"wrote {a.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
