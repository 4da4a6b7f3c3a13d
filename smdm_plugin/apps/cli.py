"""The ``smdm`` command.

* ``smdm bench``      — wall-clock of dense vs sparse training / sampling steps (MDM size);
  ``smdm bench keyframes`` times batched VW alone.
* ``smdm ablate``     — A/B ablation runner (``smdm_plugin/configs/ablations/*.yaml``) on real motion.
* ``smdm demo``       — keyframes and dense-vs-sparse training on CMU motion capture (BVH).
* ``smdm run ...``    — run an upstream script (MDM, priorMDM, MotionDiffuse) in sparse mode.
* ``smdm keyframes``  — keyframes of one BVH clip (reconstruction error per method and rate).

Subcommand modules are imported lazily, so ``smdm --help`` is fast and ``smdm run`` does not
import the benchmark code.
"""
from __future__ import annotations

import argparse
import sys
from typing import List, Optional

COMMANDS = {
    "bench": "time dense vs sparse training / sampling steps (MDM size); 'bench keyframes': VW alone",
    "ablate": "run an ablation grid (YAML) on real motion; table, CSV, loss curves",
    "demo": "keyframes + dense-vs-sparse training on CMU motion capture (BVH), no download",
    "run": "run an upstream MDM / priorMDM / MotionDiffuse script in sparse mode",
    "keyframes": "keyframe reconstruction error of BVH clips per selection method and rate",
}


def _usage() -> str:
    lines = ["usage: smdm <command> [options]", "", "commands:"]
    lines += [f"  {k:10s} {v}" for k, v in COMMANDS.items()]
    lines += ["", "'smdm <command> --help' for the options of a command."]
    return "\n".join(lines)


def _keyframes(argv: List[str]) -> int:
    from . import demo

    p = argparse.ArgumentParser(prog="smdm keyframes", description=COMMANDS["keyframes"])
    p.add_argument("bvh", nargs="*", help="BVH files or folders (default: as smdm demo)")
    p.add_argument("--reductions", nargs="+", type=float, default=[0.6, 0.7, 0.8, 0.9])
    p.add_argument("--frame-index-scale", type=float, default=0.1)
    p.add_argument("--plot", default=None, help="write the keyframe figure of the first window here (PNG)")
    a = p.parse_args(argv)
    files = demo.find_bvh(a.bvh or None)
    if not files:
        print(demo.NO_BVH, file=sys.stderr)
        return 2
    clips = demo.load_clips(files)
    if not clips:
        print(demo.NO_BVH, file=sys.stderr)
        return 2
    wins = demo.windows(clips, 196)
    print(demo.keyframe_markdown(demo.keyframe_study(wins, a.reductions, frame_index_scale=a.frame_index_scale)))
    if a.plot:
        name, start, w = wins[0]
        demo.plot_keyframes(w, f"{name} frames {start}-{start + len(w) - 1}", 0.8, a.plot,
                            frame_index_scale=a.frame_index_scale)
        print(f"wrote {a.plot}")
    return 0


def main(argv: Optional[List[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(_usage())
        return 0
    if argv[0] in ("-V", "--version"):
        from .. import __version__

        print(f"smdm-plugin {__version__}")
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd == "bench":
        from .bench import main as bench_main

        return int(bench_main(rest) or 0)
    if cmd == "ablate":
        from .ablate import main as ablate_main

        return int(ablate_main(rest) or 0)
    if cmd == "demo":
        from .demo import main as demo_main

        return int(demo_main(rest) or 0)
    if cmd == "run":
        try:
            from ..integrations.launcher import main_run
        except ImportError as e:  # the launcher ships with the integrations
            print(f"smdm run: the launcher is not available ({e})", file=sys.stderr)
            return 2
        return int(main_run(rest) or 0)
    if cmd == "keyframes":
        return _keyframes(rest)
    print(f"smdm: unknown command {cmd!r}\n\n{_usage()}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
