"""MDM's calls made ready for graph capture (this family's ``FamilySpec.preparer``, also DoubleTake's):
text encoded before the graph, strings dropped, tensors on the motion's device, classifier-free
guidance's unconditional pass folded into zeroed text features (exact in eval mode)."""
from __future__ import annotations

from typing import Any, Callable, Optional, Tuple

import torch
import torch.nn as nn

from ...runtime.compile import CallPreparer, to_device as _to


def _split_call(args: tuple, kwargs: dict) -> Tuple[Any, Any, Any]:
    x = args[0] if args else kwargs.get("x")
    t = args[1] if len(args) > 1 else kwargs.get("timesteps")
    y = args[2] if len(args) > 2 else kwargs.get("y")
    return x, t, y


def _join_call(args: tuple, kwargs: dict, x: Any, t: Any, y: Any) -> Tuple[tuple, dict]:
    args, kwargs = list(args), dict(kwargs)
    for i, (key, value) in enumerate((("x", x), ("timesteps", t), ("y", y))):
        if len(args) > i:
            args[i] = value
        elif key in kwargs:
            kwargs[key] = value
    return tuple(args), kwargs


def _is_strings(value: Any) -> bool:
    return isinstance(value, str) or (isinstance(value, (list, tuple)) and len(value) > 0
                                      and all(isinstance(v, str) for v in value))


def _zeros_like_text(enc: Any) -> Any:
    if isinstance(enc, tuple):          # DiP's BERT encoder: (features, padding mask); only features zeroed
        return (torch.zeros_like(enc[0]),) + tuple(enc[1:])
    return torch.zeros_like(enc)


class _PassThroughEncoder:
    """``model.encode_text`` that returns features already computed (tensor or tuple of tensors) and
    encodes anything else (strings) with the original encoder."""

    def __init__(self, original: Callable) -> None:
        self.original = original

    def __call__(self, raw: Any, *a: Any, **kw: Any) -> Any:
        if isinstance(raw, torch.Tensor) or (isinstance(raw, tuple) and raw and isinstance(raw[0], torch.Tensor)):
            return raw
        return self.original(raw, *a, **kw)


#: DiP's DistilBERT features are padded (masked tokens) to a multiple of this many tokens
TEXT_TOKEN_BUCKET = 64


def pad_text_tokens(enc: Tuple[torch.Tensor, ...], bucket: int = TEXT_TOKEN_BUCKET) -> Tuple[torch.Tensor, ...]:
    """DiP's BERT text features ``(features [L, B, d], padding mask [B, L] bool, True = no token)``
    padded with masked tokens to the next multiple of ``bucket`` tokens: the batch's longest
    caption no longer sets a shape (one graph for every batch up to ``bucket`` tokens). Exact:
    masked keys get zero attention weight."""
    if len(enc) != 2 or not all(isinstance(t, torch.Tensor) for t in enc) or enc[0].dim() != 3 or enc[1].dim() != 2:
        return enc
    feats, mask = enc
    L = feats.shape[0]
    target = max(bucket, -(-L // bucket) * bucket)
    if target == L or mask.shape[1] != L:
        return enc
    feats = torch.cat([feats, feats.new_zeros(target - L, *feats.shape[1:])], dim=0)
    mask = torch.cat([mask, mask.new_ones(mask.shape[0], target - L)], dim=1)
    return feats, mask


def _mdm_text_encoder(model: nn.Module) -> Optional[Callable]:
    enc = getattr(model, "encode_text", None)
    if isinstance(enc, _PassThroughEncoder):
        return enc.original
    if enc is not None:
        return enc
    return getattr(model, "text_encoder", None)   # TinyMDM


def prepare_mdm(model: nn.Module, args: tuple, kwargs: dict) -> Tuple[tuple, dict]:
    """MDM / DiP / doubleTake_MDM / TinyMDM calls ``(x [B, J, F, N], timesteps [B], y)``: text
    encoded before the graph (``y['text_embed']``; for ``doubleTake_MDM`` also ``y['text']``),
    strings dropped, tensors on ``x``'s device, and in eval mode ``y['uncond']`` folded into zeroed
    text features (MDM's ``mask_cond(force_mask=True)`` is exactly that)."""
    x, t, y = _split_call(args, kwargs)
    if not isinstance(x, torch.Tensor):
        return args, kwargs
    device = x.device
    x = x.contiguous()                               # x_t's strides change between steps: one graph
    t = _to(t, device)
    if isinstance(y, dict):
        y = dict(y)                                  # never write into the caller's dict
        cond_mode = str(getattr(model, "cond_mode", ""))
        text_cond = "text" in cond_mode and "action" not in cond_mode
        if text_cond and "text_embed" not in y and _is_strings(y.get("text")):
            encoder = _mdm_text_encoder(model)
            if encoder is not None:
                enc = encoder(list(y["text"]) if isinstance(y["text"], tuple) else y["text"])
                if getattr(model, "encode_text", None) is None:       # TinyMDM: [B, dim] -> [1, B, dim]
                    enc = enc.reshape(1, x.shape[0], -1)
                y["text_embed"] = enc
        if isinstance(y.get("text_embed"), tuple):
            y["text_embed"] = pad_text_tokens(y["text_embed"])
        uncond = y.get("uncond", False)   # True, or priorMDM's second take: 1.0
        if text_cond and isinstance(uncond, (bool, int, float)) and not model.training and "text_embed" in y:
            if uncond:
                y["text_embed"] = _zeros_like_text(y["text_embed"])
            y.pop("uncond", None)
        if "text_embed" in y and isinstance(getattr(model, "encode_text", None), _PassThroughEncoder):
            y["text"] = y["text_embed"]               # forwards that always call encode_text(y['text'])
        y = {k: (tuple(_to(v, device) for v in val) if isinstance(val, tuple) and not _is_strings(val)
                 else _to(val, device))
             for k, val in y.items() if not _is_strings(val)}
    return _join_call(args, kwargs, x, t, y)


#: upstream's ``GaussianDiffusion.training_losses`` parameters, in order (MDM, DiP, priorMDM)
LOSS_PARAMETERS = ("model", "x_start", "t", "model_kwargs", "noise", "dataset")


def loss_preparer(model: nn.Module) -> Callable[[tuple, dict], Tuple[tuple, dict]]:
    """``prepare(args, kwargs)`` of a call ``diffusion.training_losses(model, x_start [B, J, F, N],
    t [B], model_kwargs={'y': y}, noise=None, dataset=None)`` (MDM's, DiP's, priorMDM's) for
    :func:`~smdm_plugin.runtime.compile.compile_training_losses`: ``y`` prepared as ``model``'s
    call (:func:`prepare_mdm`: text encoded, strings dropped) and, when no ``noise`` is given,
    upstream's noise drawn here, eagerly, by torch's generator (``torch.randn_like(x_start)``,
    upstream's first draw there), not by the graph's random-number code. A call of another shape is
    left as it is."""
    def prepare(args: tuple, kwargs: dict) -> Tuple[tuple, dict]:
        if len(args) > len(LOSS_PARAMETERS) or not set(kwargs) <= set(LOSS_PARAMETERS):
            return args, kwargs
        bound = dict(zip(LOSS_PARAMETERS, args))
        if set(bound) & set(kwargs):
            return args, kwargs
        bound.update(kwargs)
        x, t, model_kwargs = bound.get("x_start"), bound.get("t"), bound.get("model_kwargs")
        if not isinstance(x, torch.Tensor) or not isinstance(model_kwargs, dict) \
                or not isinstance(model_kwargs.get("y"), dict):
            return args, kwargs
        (x, t, y), _ = prepare_mdm(model, (x, t, model_kwargs["y"]), {})
        bound.update(x_start=x, t=t, model_kwargs={**model_kwargs, "y": y})
        if bound.get("noise") is None:
            bound["noise"] = torch.randn_like(x)
        first = bound.pop("model")
        return (first,), bound

    return prepare


class MDMPreparer(CallPreparer):
    """:func:`prepare_mdm`; a compiled model's ``encode_text`` passes features already computed
    through (forwards that always call ``encode_text(y['text'])``)."""

    def prepare(self, model: nn.Module, args: tuple, kwargs: dict) -> Tuple[tuple, dict]:
        return prepare_mdm(model, args, kwargs)

    def attach(self, model: nn.Module) -> None:
        encoder = getattr(model, "encode_text", None)
        if encoder is not None and not isinstance(encoder, _PassThroughEncoder):
            model.encode_text = _PassThroughEncoder(encoder)

    def detach(self, model: nn.Module) -> None:
        enc = model.__dict__.get("encode_text")
        if isinstance(enc, _PassThroughEncoder):
            model.encode_text = enc.original


PREPARER = MDMPreparer()
