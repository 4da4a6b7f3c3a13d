"""How keyframe tokens go through the wrapped transformer: a registry of backends (``masked``, the
reference; ``compact``, static shapes; ``varlen``, packed rows with no padding) and the one dispatch."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Tuple

import torch
import torch.nn as nn

from .attention import aligned_key_bias, compute_dtype, float_mask
from .checks import static_shapes
from .fsq import FSQMultiheadAttention, fold_keys
from .layers import stock_stack
from .packed_attention import supports_packed, varlen_packed
from .plan import KeyframePlan
from .registry import Registry
from .rows import arange_rows, gather_rows

Backend = Callable[..., Tuple[torch.Tensor, torch.Tensor]]


@dataclass(frozen=True)
class AttentionBackend:
    """A registered backend and its capabilities: ``available(device)`` (it can run there),
    ``static_shapes`` (no data-dependent shapes or host syncs: usable under ``torch.compile`` and
    on the static path), ``supports(inner)`` (it can run that wrapped module's layers),
    ``padded_lead`` (it can run calls whose caller pads some lead tokens)."""

    fn: Backend
    available: Callable[[torch.device], bool] = lambda d: True
    static_shapes: bool = True
    supports: Callable[[nn.Module], bool] = lambda inner: True
    padded_lead: bool = True


#: the attention backends by name (``SparseConfig.attention_backend`` is validated against it + auto)
BACKENDS: Registry[AttentionBackend] = Registry(
    "attention backend", holds=AttentionBackend, reserved=("auto",),
    fields=dict(fn="callable", available="callable", supports="callable", static_shapes="a bool", padded_lead="a bool"))
#: where a backend cannot run (capability check failed): the backend that always can
FALLBACK = "compact"


def register_backend(name: str, fn: Backend, available: Callable[[torch.device], bool] = lambda d: True, *,
                     static_shapes: bool = True, supports: Callable[[nn.Module], bool] = lambda inner: True,
                     padded_lead: bool = True, replace: bool = False) -> AttentionBackend:
    """Register ``fn`` under ``name`` with its capabilities (see :class:`AttentionBackend`); a taken
    name is a ``ValueError`` unless ``replace``, ``auto`` (the automatic choice) always. ``fn(inner, x, plan,
    lead, memory=None, memory_key_padding_mask=None, lead_padding=None) -> (h [R, d], rows [lead + K, B] long)`` runs
    the ``lead`` tokens and the plan's keyframes of sequence-first ``x [S, B, d]`` through ``inner``,
    attending to each other only: ``rows[s, b]`` is the row of ``h`` for lead token ``s`` /
    keyframe slot ``s - lead`` of sample ``b`` (padded slots may point anywhere valid)."""
    return BACKENDS.register(name, AttentionBackend(fn, available, static_shapes, supports, padded_lead),
                              replace=replace)


def available_backends(device: torch.device) -> list:
    return [n for n in BACKENDS.names() if BACKENDS.get(n).available(torch.device(device))]


def resolve_backend_name(name: str, device: torch.device, inner: Optional[nn.Module] = None) -> str:
    """The backend a call uses — the one dispatch: ``auto`` is ``varlen`` in eager mode on the CPU
    and ``compact`` elsewhere (accelerators, where launches and syncs cost more than padded rows,
    and under ``torch.compile``, which needs static shapes); a backend whose capabilities do not
    fit (not available on ``device``, dynamic shapes while tracing or on the static path, cannot
    run ``inner``'s layers) becomes :data:`FALLBACK`."""
    return _resolve(name, device, inner)[0]


def _resolve(name: str, device: torch.device, inner: Optional[nn.Module], padded_lead: bool = False
             ) -> Tuple[str, str]:
    """:func:`resolve_backend_name`'s choice and, where it falls back, why (else ``""``)."""
    device = torch.device(device)
    if name == "auto":
        name = "varlen" if device.type == "cpu" and not static_shapes() else FALLBACK
    b = BACKENDS.get(name)
    if not b.available(device):
        return FALLBACK, f"it is not available on {device.type}"
    if static_shapes() and not b.static_shapes:
        return FALLBACK, "it has dynamic shapes (torch.compile or the static path needs static ones)"
    if inner is not None and not b.supports(inner):
        return FALLBACK, f"it cannot run the layers of {type(inner).__name__}"
    if padded_lead and not b.padded_lead:
        return FALLBACK, "it cannot run padded lead tokens"
    return name, ""


def get_backend(name: str, device: torch.device, inner: Optional[nn.Module] = None,
                padded_lead: bool = False) -> Backend:
    """The backend function :func:`resolve_backend_name` picks for ``name`` on ``device`` (for a
    call whose lead tokens are padded when ``padded_lead``); a backend asked for by name that
    falls back says so once (:func:`warn_fallback`)."""
    used, why = _resolve(name, device, inner, padded_lead)
    if why and name not in ("auto", used):
        warn_fallback(name, used, why)
    return BACKENDS.get(used).fn


#: (backend asked for, backend used, why) already warned about in this process
_WARNED: set = set()


def warn_fallback(asked: str, used: str, why: str) -> None:
    """Warn once per process and (``asked``, ``used``, ``why``) that a backend asked for by name
    does not run a call and ``used`` does; silent while ``torch.compile`` traces."""
    key = (asked, used, why)
    if key in _WARNED or torch.compiler.is_compiling():
        return
    import warnings

    _WARNED.add(key)
    warnings.warn(f"attention backend {asked!r} falls back to {used!r}: {why}", RuntimeWarning, stacklevel=3)


# ---------------------------------------------------------------------------------- helpers
def _call_inner(inner: nn.Module, x: torch.Tensor, pad: Optional[torch.Tensor], memory: Optional[torch.Tensor],
                memory_key_padding_mask: Optional[torch.Tensor]) -> torch.Tensor:
    """Run the wrapped module on sequence-first ``x [S, B, d]`` whatever its own layout."""
    bf = bool(getattr(inner.layers[0].self_attn, "batch_first", False))
    if bf:
        x = x.transpose(0, 1)
        memory = memory.transpose(0, 1) if memory is not None else None
    attns = [layer.self_attn for layer in inner.layers if isinstance(layer.self_attn, FSQMultiheadAttention)]
    with fold_keys(attns, x):                  # training: all layers' FSQ folds at once
        if memory is None:
            out = inner(x, src_key_padding_mask=pad)
        else:
            out = inner(x, memory, tgt_key_padding_mask=pad, memory_key_padding_mask=memory_key_padding_mask)
    return out.transpose(0, 1) if bf else out


def _slot_rows(plan: KeyframePlan, lead: int) -> torch.Tensor:
    """``[lead + K, B]`` long: the row ``position * B + b`` of every lead token and plan slot in a
    sequence-first ``[(lead + N) * B, ...]`` tensor."""
    if not lead:
        return plan.rows
    B = plan.batch
    return torch.cat([arange_rows(lead, B, plan.rows.device), plan.rows + lead * B], 0)


def _lead_keep(plan: KeyframePlan, lead: int, lead_padding: Optional[torch.Tensor]) -> torch.Tensor:
    """bool ``[B, lead]``: lead tokens that take part (all, unless the caller pads some)."""
    if lead_padding is not None:
        return ~lead_padding.to(torch.bool)
    return plan.mask.new_ones(plan.batch, lead)


def _key_bias(plan: KeyframePlan, lead: int, lead_padding: Optional[torch.Tensor], dtype: torch.dtype
              ) -> torch.Tensor:
    """Additive key padding mask ``[B, lead + K]`` (0 kept / -inf padded lead tokens and empty
    slots), made once per call: a float mask goes through every layer's attention as it is (a
    bool one is converted again in each layer). A looked-up plan carries it (``plan.key_bias``)."""
    if plan.key_bias is not None and lead <= 1:
        bias = plan.key_bias[:, 1 - lead:]
        if lead and lead_padding is not None:                       # the caller's padding of its lead token
            bias = torch.cat([bias[:, :1].masked_fill(lead_padding.to(torch.bool), float("-inf")), bias[:, 1:]], 1)
        return bias if bias.dtype == dtype else bias.to(dtype)
    pad = ~plan.valid
    if lead:
        lead_pad = plan.valid.new_zeros(plan.batch, lead) if lead_padding is None else lead_padding.to(torch.bool)
        pad = torch.cat([lead_pad, pad], 1)
    return torch.zeros(pad.shape, dtype=dtype, device=pad.device).masked_fill_(pad, float("-inf"))


# ---------------------------------------------------------------------------------- masked
def masked_backend(inner: nn.Module, x: torch.Tensor, plan: KeyframePlan, lead: int,
                   memory: Optional[torch.Tensor] = None, memory_key_padding_mask: Optional[torch.Tensor] = None,
                   lead_padding: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    S, B, d = x.shape
    keep = torch.cat([_lead_keep(plan, lead, lead_padding), plan.mask], 1)
    out = _call_inner(inner, x, ~keep, memory, memory_key_padding_mask)
    rows = _slot_rows(plan, lead)
    return out.reshape(S * B, d), rows


# ---------------------------------------------------------------------------------- compact
def compact_backend(inner: nn.Module, x: torch.Tensor, plan: KeyframePlan, lead: int,
                    memory: Optional[torch.Tensor] = None, memory_key_padding_mask: Optional[torch.Tensor] = None,
                    lead_padding: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    S, B, d = x.shape
    R = lead + plan.capacity
    if not (torch.is_grad_enabled() and x.requires_grad):   # the slots' frames by index; lead tokens as they are
        slots = torch.gather(x[lead:], 0, plan.index.t().unsqueeze(-1).expand(R - lead, B, d))
        rows = (torch.cat([x[:lead], slots]) if lead else slots).view(R * B, d)
    else:                                  # one gather (with autograd: one scatter back, not two + a sum)
        rows = gather_rows(x.reshape(S * B, d), _slot_rows(plan, lead).reshape(-1))      # [R·B, d]
    # the key bias in the dtype the attention runs in (autocast's): cast once, not in every layer
    dtype = compute_dtype(x)
    bias = _key_bias(plan, lead, lead_padding, dtype)
    stack = stock_stack(inner)
    if stack is None:                      # custom layers or hooks: the modules, as they are
        out = _call_inner(inner, rows.view(R, B, d), bias, memory, memory_key_padding_mask).reshape(R * B, d)
    else:                                  # stock layers as functions on the rows (core/layers.py)
        memory_bias = None
        if memory_key_padding_mask is not None:
            memory_bias = aligned_key_bias(float_mask(memory_key_padding_mask, dtype))
        out = stack.run_rows(rows, R, aligned_key_bias(bias), memory, memory_bias)
    return out, arange_rows(R, B, x.device)


# ---------------------------------------------------------------------------------- varlen
def varlen_backend(inner: nn.Module, x: torch.Tensor, plan: KeyframePlan, lead: int,
                   memory: Optional[torch.Tensor] = None, memory_key_padding_mask: Optional[torch.Tensor] = None,
                   lead_padding: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Packed tokens with no padding through PyTorch's own layers (:func:`varlen_packed`); only
    the attention pads. Custom layers, hooks on layers, padded lead tokens and static shapes
    (``torch.compile``, :func:`~smdm_plugin.core.checks.static_mode`) fall back to ``compact``."""
    if lead_padding is not None or static_shapes() or not supports_packed(inner):
        return compact_backend(inner, x, plan, lead, memory, memory_key_padding_mask, lead_padding)
    keep = torch.cat([plan.mask.new_ones(plan.batch, lead), plan.mask], 1)
    h, pq = varlen_packed(inner, x, keep, memory, memory_key_padding_mask)
    # packed rows are batch-major in sequence order: sample b's lead tokens, then its keyframes
    start = pq.cu[:-1]                                                 # [B]
    slot = torch.arange(lead + plan.capacity, device=x.device)[:, None]
    ok = torch.cat([plan.mask.new_ones(lead, plan.batch), plan.valid.t()], 0)
    rows = torch.where(ok, start[None, :] + slot, start[None, :])
    return h, rows


register_backend("masked", masked_backend)
register_backend("compact", compact_backend)
register_backend("varlen", varlen_backend, static_shapes=False, supports=supports_packed, padded_lead=False)
