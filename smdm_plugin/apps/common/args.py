"""Arguments shared by the ``smdm`` commands: every numeric option range-checked by argparse
(a bad value is one line naming the option, exit status 2, no traceback), devices that exist,
output paths that are never overwritten without ``--overwrite``, and the common flags every
command takes (:func:`add_common_flags`: ``--device``, ``--threads``, ``--no-progress`` / ``--progress``,
``--quiet``)."""
from __future__ import annotations

import argparse
import os
from typing import TYPE_CHECKING, Any, Callable, Optional

if TYPE_CHECKING:
    import torch

# the range-checked types live in core (the --sparse_* options use them too); re-exported here
from ...support.argtypes import float_range, int_range, str2bool

#: argparse ``type`` of every ``--seed``: what torch's generators take (a larger int overflowed inside torch)
seed_type = int_range(0, 2 ** 63 - 1)

__all__ = ["int_range", "float_range", "str2bool", "seed_type", "existing_path", "positional_type", "output_path",
           "device_type", "compile_backend",
           "resolve_device", "add_overwrite", "add_common_flags", "progress_of", "note_printer", "COMMON_FLAGS"]


def existing_path(kind: str = "any") -> Callable[[str], str]:
    """argparse ``type``: a path that exists (``kind``: ``"file"``, ``"dir"`` or ``"any"``)."""
    if kind not in ("file", "dir", "any"):
        raise ValueError(f"existing_path: kind must be 'file', 'dir' or 'any', got {kind!r}")

    def parse(text: str) -> str:
        if not os.path.exists(text):
            raise argparse.ArgumentTypeError(f"no such {'folder' if kind == 'dir' else 'file'}: {text!r}")
        if kind == "file" and os.path.isdir(text):
            raise argparse.ArgumentTypeError(f"{text!r} is a folder, expected a file")
        if kind == "dir" and not os.path.isdir(text):
            raise argparse.ArgumentTypeError(f"{text!r} is not a folder")
        return text

    parse.__name__ = "path"
    return parse


def positional_type(p: argparse.ArgumentParser, a: argparse.Namespace, dest: str, parse: Callable[[str], str],
                    name: Optional[str] = None) -> None:
    """Check a positional argument (``a.<dest>``: one value or a list) with ``parse`` (an argparse
    ``type``) after parsing, not as its ``type``: argparse types a positional as soon as a value
    fills it, so the value of a mistyped option (``--rates 0``) was checked as the positional (``no
    such file: '0'``) before the unknown option was named. A bad value: ``p.error`` naming
    ``name`` (default ``dest``), exit 2."""
    value = getattr(a, dest)
    try:
        setattr(a, dest, [parse(v) for v in value] if isinstance(value, list) else parse(value))
    except argparse.ArgumentTypeError as e:
        p.error(f"argument {name or dest}: {e}")


def output_path(kind: str = "folder") -> Callable[[str], str]:
    """argparse ``type``: where a command writes (``kind``: ``"folder"`` or ``"file"``), not empty (an
    empty ``--out`` would be the working folder, or no output at all: refused, never read as either)."""
    if kind not in ("folder", "file"):
        raise ValueError(f"output_path: kind must be 'folder' or 'file', got {kind!r}")

    def parse(text: str) -> str:
        if not text.strip():
            raise argparse.ArgumentTypeError(f"expected a {kind} path, got {text!r}")
        return text

    parse.__name__ = "path"
    return parse


def device_type(text: str) -> str:
    """argparse ``type``: ``auto``, ``cpu``, ``cuda``/``cuda:N`` or ``mps``, and only one this machine has."""
    if text == "auto":
        return text
    import torch  # here, so that parsing the other options (and --help) does not import torch

    try:
        dev = torch.device(text)
    except (RuntimeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected auto, cpu, cuda, cuda:N or mps, got {text!r}") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise argparse.ArgumentTypeError(f"{text}: CUDA is not available on this machine")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise argparse.ArgumentTypeError(f"{text}: this machine has {torch.cuda.device_count()} "
                                             "CUDA device(s)")
    elif dev.type == "mps":
        mps = getattr(torch.backends, "mps", None)
        if mps is None or not mps.is_available():
            raise argparse.ArgumentTypeError(f"{text}: MPS is not available on this machine")
    elif dev.type != "cpu":
        raise argparse.ArgumentTypeError(f"expected auto, cpu, cuda, cuda:N or mps, got {text!r}")
    return text


def compile_backend(text: str) -> str:
    """argparse ``type``: a ``torch.compile`` backend torch knows (``torch._dynamo.list_backends()``,
    entry-point and registered backends included), checked when parsed, before anything is written."""
    if text == "inductor":  # the default: no need to import the compiler to accept it
        return text
    from torch._dynamo import list_backends
    from torch._dynamo.backends.registry import lookup_backend

    from ...support.values import closest

    try:
        lookup_backend(text)
    except Exception:  # torch._dynamo.exc.InvalidBackend, or a backend that fails to load
        known = [b for b in list_backends(exclude_tags=()) if "TESTING" not in b]
        raise argparse.ArgumentTypeError(f"unknown torch.compile backend {text!r}{closest(text, known)} (known: "
                                         f"{', '.join(known)})") from None
    return text


def resolve_device(name: str = "auto") -> "torch.device":
    """The ``torch.device`` of a ``--device`` value (checked by :func:`device_type`): ``auto`` is
    CUDA when available, else MPS when available, else the CPU (one rule for every command:
    :func:`smdm_plugin.runtime.distributed.resolve_device`)."""
    from ...runtime.distributed import resolve_device as resolve

    return resolve(name if name == "auto" else device_type(name))


def add_overwrite(p: argparse.ArgumentParser) -> None:
    """``--overwrite``: without it, a command refuses an existing output file or non-empty folder."""
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing output files / write into a non-empty output folder")


COMMON_FLAGS = ("--device", "--threads", "--no-progress", "--progress", "--quiet")
DEVICE_HELP = "auto (CUDA, else MPS, else CPU), cpu, cuda, cuda:N or mps (default {default})"


class _NotApplicable(argparse.Action):
    """A common flag this command cannot honour: parsed, then refused with one line saying why."""

    def __init__(self, option_strings, dest, why: str = "", **kwargs: Any) -> None:
        self.why = why
        super().__init__(option_strings, dest, help=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        parser.error(f"argument {option_string}: does not apply to {parser.prog} ({self.why})")


class _StoreTrueApart(argparse._StoreTrueAction):
    """``store_true`` refused beside the flag ``apart`` (its dest), in either order: ``--quiet`` shows no
    progress, so ``--progress`` with it would be dropped."""

    def __init__(self, option_strings, dest, apart: str = "", **kwargs: Any) -> None:
        self.apart = apart
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        if getattr(namespace, self.apart, False):
            parser.error(f"argument {option_string}: not allowed with argument --{self.apart.replace('_', '-')}")
        super().__call__(parser, namespace, values, option_string)


def add_common_flags(p: Any, *, device: Optional[str] = "auto", threads: bool = True,
                     threads_default: Optional[int] = None, progress: bool = True, quiet: bool = True,
                     why_not: str = "", device_help: str = "") -> None:
    """Add the common flags to parser (or group) ``p``, one meaning everywhere:

    * ``--device DEV`` (default ``device``; ``None``: the command has no device) — :func:`device_type`
      (``device_help``: what ``auto`` means for this command, when it says more than the default help);
    * ``--threads N`` (default ``threads_default``: the automatic choice of ``common.threads``);
    * ``--no-progress`` — no progress bars or per-step progress lines; without it bars show only
      when stderr is a terminal (:func:`smdm_plugin.support.progress.bars_on`), ``--progress`` shows
      them whatever stderr is (a log file then holds every redraw);
    * ``--quiet`` — ``--no-progress`` and no notes (what the command is doing, where it wrote):
      results, warnings and errors still print (:func:`progress_of`, :func:`note_printer`).

    A flag the command cannot honour (``device=None``, ``threads=False``, ...) is still parsed and
    refused with one argparse line naming ``why_not`` (exit status 2)."""
    def refuse(flag: str, nargs: int) -> None:
        p.add_argument(flag, action=_NotApplicable, why=why_not or "not used by this command", nargs=nargs)

    if device is not None:
        p.add_argument("--device", type=device_type, default=device, help=device_help or DEVICE_HELP.format(default=device))
    else:
        refuse("--device", 1)
    if threads:
        from .threads import THREADS_HELP

        p.add_argument("--threads", type=int_range(1, 1024), default=threads_default, metavar="N",
                       help=THREADS_HELP if threads_default is None else f"CPU threads for torch (default {threads_default})")
    else:
        refuse("--threads", 1)
    if progress:
        bars = p.add_mutually_exclusive_group()        # (both given: one of them would be dropped)
        bars.add_argument("--no-progress", action="store_true", help="no progress bars or per-step progress lines "
                          "(without it, bars show only when stderr is a terminal)")
        bars.add_argument("--progress", action=_StoreTrueApart, apart="quiet",
                          help="progress bars even when stderr is not a terminal")
    else:
        refuse("--no-progress", 0)
        refuse("--progress", 0)
    if quiet:
        p.add_argument("--quiet", action=_StoreTrueApart, apart="progress",
                       help="--no-progress, and no notes: only results, warnings and errors print")
    else:
        refuse("--quiet", 0)


def progress_of(args: argparse.Namespace) -> bool | str:
    """Whether the command shows progress: neither ``--no-progress`` nor ``--quiet`` was given
    (per-step lines then print; bars show where :func:`smdm_plugin.support.progress.bars_on` says);
    ``"always"`` (:data:`smdm_plugin.support.progress.ALWAYS`: bars whatever stderr is) with ``--progress``."""
    if getattr(args, "no_progress", False) or getattr(args, "quiet", False):
        return False
    return "always" if getattr(args, "progress", False) else True


def note_printer(args: argparse.Namespace) -> Callable[..., None]:
    """``print`` for a command's notes (``print(msg, file=sys.stderr)`` as usual); silent under ``--quiet``."""
    if getattr(args, "quiet", False):
        return lambda *a, **kw: None
    return print
