"""Argument types shared by the ``smdm`` commands: every numeric option range-checked by argparse
(a bad value is one line naming the option, exit status 2, no traceback), devices that exist,
output paths that are never overwritten without ``--overwrite``."""
from __future__ import annotations

import argparse
import os
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    import torch

# the range-checked types live in core (the --sparse_* options use them too); re-exported here
from ...core.argtypes import float_range, int_range, str2bool

__all__ = ["int_range", "float_range", "str2bool", "existing_path", "device_type", "resolve_device",
           "add_overwrite"]


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


def resolve_device(name: str = "auto") -> "torch.device":
    """The ``torch.device`` of a ``--device`` value (checked by :func:`device_type`): ``auto`` is
    CUDA when available, else MPS when available, else the CPU (one rule for every command:
    :func:`smdm_plugin.integrations.distributed.resolve_device`)."""
    from ...integrations.distributed import resolve_device as resolve

    return resolve(name if name == "auto" else device_type(name))


def add_overwrite(p: argparse.ArgumentParser) -> None:
    """``--overwrite``: without it, a command refuses an existing output file or non-empty folder."""
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing output files / write into a non-empty output folder")
