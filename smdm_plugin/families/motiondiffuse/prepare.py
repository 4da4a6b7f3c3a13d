"""MotionDiffuse's calls made ready for graph capture (this family's ``FamilySpec.preparer``): the
text encoded before the graph, ``text`` dropped, tensors on the motion's device."""
from __future__ import annotations

from typing import Tuple

import torch
import torch.nn as nn

from ...runtime.compile import to_device as _to


def prepare_motiondiffuse(model: nn.Module, args: tuple, kwargs: dict) -> Tuple[tuple, dict]:
    """MotionDiffuse's ``forward(x [B, T, D], timesteps, length=, text=, xf_proj=, xf_out=)``: the
    text encoded before the graph (``xf_proj``, ``xf_out``; upstream encodes inside forward when
    they are absent), ``text`` dropped, tensors on ``x``'s device."""
    x = args[0] if args else kwargs.get("x")
    if not isinstance(x, torch.Tensor):
        return args, kwargs
    kwargs = dict(kwargs)
    x = x.contiguous()
    names = ("timesteps", "length", "text", "xf_proj", "xf_out")
    for name, value in zip(names, args[1:]):
        kwargs[name] = value
    args = (x,)
    if (kwargs.get("xf_proj") is None or kwargs.get("xf_out") is None) and kwargs.get("text") is not None:
        text = kwargs["text"]
        B = x.shape[0]
        if len(text) != B:                           # upstream's DataParallel slice
            index = x.device.index or 0
            text = text[index * B: index * B + B]
        kwargs["xf_proj"], kwargs["xf_out"] = model.encode_text(text, x.device)
    kwargs.pop("text", None)
    length = kwargs.get("length")
    if isinstance(length, (list, tuple)) and all(isinstance(v, int) for v in length):
        kwargs["length"] = torch.tensor(length, dtype=torch.long)   # Python ints would be guarded one by one
    return args, {k: _to(v, x.device) for k, v in kwargs.items()}


PREPARER = prepare_motiondiffuse
