"""The ``smdm`` command: one entry point dispatching to the sub-commands of :data:`COMMANDS`."""
from __future__ import annotations

import importlib
import os
import signal
import sys
from typing import Callable, Dict, List, Optional, Tuple

# command -> ("module" or "module:function" whose function(argv) -> int, default function main; one-line help)
COMMANDS: Dict[str, Tuple[str, str]] = {
    "bench": ("smdm_plugin.apps.bench",
              "time dense vs sparse training / sampling steps (MDM size); 'bench keyframes': VW alone"),
    "ablate": ("smdm_plugin.apps.ablate", "run an ablation grid (YAML) on real motion; table, CSV, loss curves; "
               "--config quality_compute: the quality-versus-compute study"),
    "demo": ("smdm_plugin.apps.demo", "keyframes + dense-vs-sparse training on CMU motion capture (BVH), no download"),
    "train": ("smdm_plugin.apps.train", "train TinyMDM (dense or --sparse) on HumanML3D-format motion; "
              "under torchrun: DistributedDataParallel"),
    "run": ("smdm_plugin.integrations.launcher:main_run",
            "run an upstream MDM / priorMDM / MotionDiffuse script in sparse mode"),
    "inbetween": ("smdm_plugin.apps.inbetween",
                  "in-betweening: a motion through your keyframes (BVH / .npy), dense and sparse, with a GIF"),
    "render": ("smdm_plugin.apps.render", "a saved motion (.npy joints / HumanML3D features, BVH) as an animated GIF"),
    "keyframes": ("smdm_plugin.apps.keyframes", "keyframe reconstruction error of BVH clips per selection method and rate"),
    "evaluator": ("smdm_plugin.apps.evaluator", "'evaluator train': train a T2M evaluator on your captioned motion"),
    "eval": ("smdm_plugin.apps.evaluate", "FID, R-precision, diversity, jitter, skating of motions or a model"),
    "clips": ("smdm_plugin.apps.clips", "list the embedded CMU clips, or export one as a .npy motion file"),
}


def _usage() -> str:
    lines = ["usage: smdm <command> [options]", "", "commands:"]
    lines += [f"  {k:10s} {v[1]}" for k, v in COMMANDS.items()]
    lines += ["", "'smdm <command> --help' (or 'smdm help <command>') for the options of a command; 'smdm --version'."]
    return "\n".join(lines)


def entry_point(command: str) -> Callable[[List[str]], Optional[int]]:
    """The function that runs ``command`` (imported now)."""
    target = COMMANDS[command][0]
    module, _, func = target.partition(":")
    return getattr(importlib.import_module(module), func or "main")


def main(argv: Optional[List[str]] = None) -> int:
    argv_given = argv is not None
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv:
        print(_usage(), file=sys.stderr)
        return 2
    if argv[0] in ("-h", "--help", "help"):
        if len(argv) == 1:
            print(_usage())
            return 0
        if len(argv) > 2:
            print(f"smdm: error: {argv[0]} takes at most one command name, got {' '.join(argv[1:])!r}",
                  file=sys.stderr)
            return 2
        argv = [argv[1], "--help"]                    # `smdm help demo`: the command's own help
    if argv[0] in ("-V", "--version"):
        if len(argv) > 1:
            print(f"smdm: error: {argv[0]} takes no arguments, got {' '.join(argv[1:])!r}", file=sys.stderr)
            return 2
        from .. import __version__

        print(f"smdm-plugin {__version__}")
        return 0
    cmd, rest = argv[0], argv[1:]
    if cmd not in COMMANDS:
        from ..support.values import closest

        print(f"smdm: error: unknown command {cmd!r}{closest(cmd, COMMANDS)} (commands: {', '.join(COMMANDS)}; "
              "'smdm --help' for more)", file=sys.stderr)
        return 2
    from .common import signals
    from .common.threads import prepare_process

    prepare_process()  # OMP_WAIT_POLICY=PASSIVE before torch loads OpenMP (docs/threads.md)
    if cmd == "run":  # the launcher forwards Ctrl-C to the upstream command and waits for it
        return _run_command(cmd, rest)
    with signals.stop_on_signals(bound_exit=not argv_given):  # SIGTERM / SIGHUP end a command as Ctrl-C
        status = _run_command(cmd, rest)
    return signals.exit_status(status)


def _run_command(cmd: str, rest: List[str]) -> int:
    """Run ``smdm <cmd> <rest>``: its exit status, the top-level failures as one line each."""
    try:
        return int(entry_point(cmd)(rest) or 0)
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM / SIGHUP (signals.Stopped)
        by = getattr(e, "signum", signal.SIGINT)
        print(f"\nsmdm {cmd}: " + ("interrupted" if by == signal.SIGINT else f"stopped by {e}"), file=sys.stderr)
        return 130
    except FileExistsError as e:  # OutputExistsError a command did not report itself
        print(f"smdm {cmd}: error: {e}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # `smdm ... | head`: the reader left; no traceback (as the Python docs advise)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1
    except OSError as e:  # no space, read-only, permission denied ...: one line naming the path and the reason
        from ..io.outdir import describe_os_error

        print(f"smdm {cmd}: error: {describe_os_error(e)}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
