"""``smdm clips``: the CMU motion capture clips embedded in the package, listed or written out as a
motion file that every other command reads.

    smdm clips                                   # name, frames, seconds, CMU's description
    smdm clips export 05_02 --out dance.npy      # joints [N, 22, 3], metres, y up, 20 fps
    smdm clips export 05_02 --frames 0 40 100 --out poses.npy   # three of its poses [3, 22, 3]

The exported ``.npy`` is what ``smdm inbetween --keyframes``, ``smdm render`` and
``numpy.load`` read: HumanML3D's 22 joints in metres at 20 fps (``--format joints66``: the
in-package 66-D features ``[N, 66]`` instead). The clips are from the CMU Graphics Lab Motion
Capture Database (mocap.cs.cmu.edu); see ``smdm_plugin/data/README.md``.
"""
from __future__ import annotations

import argparse
import sys
from typing import List, Optional

from .common.args import add_overwrite, int_range, output_path

FORMATS = ("joints", "joints66")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="smdm clips", description=__doc__.split("\n\n")[0],
                                epilog="'smdm clips' alone lists the clips; 'smdm clips export NAME --out FILE.npy' "
                                       "writes one")
    sub = p.add_subparsers(dest="action", metavar="{list,export}")
    sub.add_parser("list", help="list the embedded clips (the default action)",
                   description="list the embedded clips: name, frames, seconds at 20 fps, CMU's description")
    e = sub.add_parser("export", help="write one clip as a .npy motion file",
                       description="write one embedded clip as a .npy motion file")
    e.add_argument("name", metavar="NAME", help="clip name as 'smdm clips' lists it, e.g. 05_02")
    e.add_argument("--out", default=None, metavar="FILE", type=output_path("file"),
                   help="the .npy file to write (default: NAME.npy in the current folder)")
    e.add_argument("--format", choices=FORMATS, default="joints",
                   help="joints: [N, 22, 3] joint positions in metres, y up (default); joints66: the in-package "
                        "features [N, 66]; both at 20 frames per second")
    e.add_argument("--frames", type=int_range(0), nargs="+", default=None, metavar="F",
                   help="write only these frames of the clip (0-based, in the order given), e.g. poses for "
                        "'smdm inbetween --keyframes' (default: every frame)")
    add_overwrite(e)
    return p


def main(argv: Optional[List[str]] = None) -> int:
    from ..io.embedded import FPS, embedded_clips, embedded_descriptions

    p = build_parser()
    a = p.parse_args(argv)
    clips = dict(embedded_clips())
    if a.action in (None, "list"):
        desc = embedded_descriptions()
        print(f"{len(clips)} CMU clips embedded in smdm-plugin (HumanML3D's 22 joints, metres, {FPS} fps):")
        print(f"  {'name':8s} {'frames':>6s} {'seconds':>7s}  description")
        for name, joints in clips.items():
            print(f"  {name:8s} {len(joints):6d} {len(joints) / FPS:7.1f}  {desc.get(name, '')}")
        print("write one out: smdm clips export NAME --out NAME.npy")
        return 0
    if a.name not in clips:
        from ..support.values import closest

        p.error(f"argument NAME: no embedded clip {a.name!r}{closest(a.name, clips)} "
                f"('smdm clips' lists the {len(clips)} clips)")
    out = a.out or f"{a.name}.npy"
    if not out.lower().endswith(".npy"):
        p.error(f"argument --out: expected a file name ending in .npy, got {out!r}")
    import os

    import numpy as np

    from ..io.files import OutputExistsError, atomic_open, check_new_file

    folder = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(folder):
        p.error(f"argument --out: the folder {folder!r} " + ("is a file, not a folder" if os.path.lexists(folder)
                                                            else "does not exist"))
    try:
        check_new_file(out, a.overwrite, what="--out")
    except OutputExistsError as e:
        p.error(str(e))
    joints = clips[a.name]
    if a.frames is not None:
        late = [f for f in a.frames if f >= len(joints)]
        if late:
            p.error(f"argument --frames: clip {a.name} has {len(joints)} frames (0..{len(joints) - 1}), got {late}")
        joints = np.asarray(joints)[a.frames]
    if a.format == "joints66":
        from ..io.representation import Representation

        arr = np.asarray(Representation("joints66").from_joints(joints), np.float32)
    else:
        arr = np.asarray(joints, np.float32)
    with atomic_open(out, "wb") as f:
        np.save(f, arr)
    print(f"wrote {out}: clip {a.name} ({embedded_descriptions().get(a.name, '')}), {a.format} "
          f"{list(arr.shape)}, {len(arr) / FPS:.1f} s at {FPS} fps")
    return 0


if __name__ == "__main__":
    sys.exit(main())
