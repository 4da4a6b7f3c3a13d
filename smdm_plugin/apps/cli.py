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
import importlib
import sys
from typing import Dict, List, Optional, Tuple

# command -> (module with ``main(argv) -> int``, one-line help)
COMMANDS: Dict[str, Tuple[str, str]] = {
    "bench": ("smdm_plugin.apps.bench",
              "time dense vs sparse training / sampling steps (MDM size); 'bench keyframes': VW alone"),
    "ablate": ("smdm_plugin.apps.ablate", "run an ablation grid (YAML) on real motion; table, CSV, loss curves"),
    "demo": ("smdm_plugin.apps.demo", "keyframes + dense-vs-sparse training on CMU motion capture (BVH), no download"),
    "run": ("smdm_plugin.integrations.launcher", "run an upstream MDM / priorMDM / MotionDiffuse script in sparse mode"),
    "inbetween": ("smdm_plugin.apps.inbetween",
                  "in-betweening: a motion through your keyframes (BVH / .npy), dense and sparse, with a GIF"),
    "render": ("smdm_plugin.apps.render", "a saved motion (.npy joints / HumanML3D features, BVH) as an animated GIF"),
    "keyframes": ("smdm_plugin.apps.cli", "keyframe reconstruction error of BVH clips per selection method and rate"),
}


def _usage() -> str:
    lines = ["usage: smdm <command> [options]", "", "commands:"]
    lines += [f"  {k:10s} {v[1]}" for k, v in COMMANDS.items()]
    lines += ["", "'smdm <command> --help' for the options of a command."]
    return "\n".join(lines)


def _keyframes(argv: List[str]) -> int:
    from . import demo

    p = argparse.ArgumentParser(prog="smdm keyframes", description=COMMANDS["keyframes"][1])
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
    if cmd not in COMMANDS:
        print(f"smdm: unknown command {cmd!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    if cmd == "keyframes":
        return _keyframes(rest)
    module = importlib.import_module(COMMANDS[cmd][0])
    entry = getattr(module, "main_run" if cmd == "run" else "main")
    return int(entry(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
