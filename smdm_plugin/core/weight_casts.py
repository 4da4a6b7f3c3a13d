"""Matmul weights in autocast's dtype, made once for the compiled calls without autograd.

Under autocast a traced sampling call casts every linear layer's weight and bias at every call and
guidance pass (a bf16 trans_enc guided call: 148 casts dense, 116 sparse; ``scripts/graph_work.py``),
though they change only with the parameters. :func:`refresh_casts` keeps them in a
:class:`~smdm_plugin.core.products.ProductStore` on the model (remade in place, marked static for
CUDA graphs); a compiled call reads them in place of the parameters (``torch.func.functional_call``,
``runtime/compile.py``): autocast's values, dense and sparse alike. Cast are only parameters that
autocast's lower-precision ops alone read (:func:`cast_parameters`; docs/modules.md).
"""
from __future__ import annotations

from typing import Dict, List, Optional, Tuple

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from .products import ProductStore, Remade
from .structure import structure_version

__all__ = ["cast_parameters", "refresh_casts"]

#: the dtypes autocast lowers matmuls to
_LOWER = (torch.bfloat16, torch.float16)
#: the module types whose ``weight`` and ``bias`` only ``F.linear`` reads
_LINEARS = (nn.Linear, nn.modules.linear.NonDynamicallyQuantizableLinear)


def _own(module: nn.Module) -> Tuple[str, ...]:
    """The names of ``module``'s own parameters that only matmuls read (a parametrized weight is not
    one: it is no parameter of the module; a Lipschitz layer's bias is)."""
    kind = type(module)
    if parametrize.is_parametrized(module):
        kind = kind.__bases__[0]
    if kind in _LINEARS:
        return ("weight", "bias")
    if kind is nn.MultiheadAttention:
        return ("in_proj_weight", "in_proj_bias")
    return ()


def cast_parameters(model: nn.Module) -> List[Tuple[str, Tensor]]:
    """``(name, parameter)`` of every parameter of ``model`` a compiled call without autograd reads
    in autocast's dtype, in module order: the weights and biases of plain linear layers (a Lipschitz
    layer's bias) and of stock multi-head attention's in-projection, float32, trainable (a frozen
    text encoder runs outside the graph), each read by one module."""
    owners: Dict[int, int] = {}
    for _, p in model.named_parameters(remove_duplicate=False):
        owners[id(p)] = owners.get(id(p), 0) + 1
    out = []
    for prefix, module in model.named_modules():
        for name in _own(module):
            p = module._parameters.get(name)
            if p is not None and p.dtype == torch.float32 and p.requires_grad and owners.get(id(p)) == 1:
                out.append((f"{prefix}.{name}" if prefix else name, p))
    return out


class _Casts(Remade):
    """The cast parameters of one model structure (the casts themselves are kept apart: the same
    tensors after a rebuild that finds the same parameters)."""

    __slots__ = ("version", "prefix", "names", "params", "held")

    def __init__(self, model: nn.Module, version: Optional[int], prefix: str) -> None:
        found = cast_parameters(model)
        self.version, self.prefix = version, prefix
        self.names = [prefix + n for n, _ in found]
        self.params = [p for _, p in found]
        self.held: Tuple[Optional[tuple], Dict[str, Tensor]] = (None, {})


def refresh_casts(model: nn.Module, device_type: str, prefix: str = "") -> Optional[Dict[str, Tensor]]:
    """``{prefix + name: parameter in autocast's dtype}`` for a call on ``device_type`` under autocast
    to bfloat16 or float16 (:func:`cast_parameters`, found once per model structure and ``prefix``),
    remade in place when a parameter changed; None without such autocast or without such parameters."""
    if device_type not in ("cpu", "cuda") or not torch.is_autocast_enabled(device_type):
        return None
    dtype = torch.get_autocast_dtype(device_type)
    if dtype not in _LOWER:
        return None
    version = structure_version()
    found = model.__dict__.get("_smdm_casts")
    if found is None or version is None or found.version != version or found.prefix != prefix:
        found = model.__dict__["_smdm_casts"] = _Casts(model, version, prefix)
    if not found.params:
        return None
    store = model.__dict__.get("_smdm_cast_store")
    if store is None:
        store = model.__dict__["_smdm_cast_store"] = ProductStore()
    with torch.autocast(device_type, enabled=False):
        held = store.get(dtype, found.params, lambda: [p.detach().to(dtype) for p in found.params])
    if found.held[0] is not held:                  # the same dict while the same tensors are held
        found.held = (held, dict(zip(found.names, held)))
    return found.held[1]
