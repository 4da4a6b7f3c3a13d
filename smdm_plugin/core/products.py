"""What a sampling call computes from parameters alone, made once outside a compiled graph.

FSQ attention's folded in-projections and the Lipschitz layers' normalised weights depend on
parameters only. Eagerly, a call without autograd keeps them in a :class:`ProductStore` (the
package's one cache of values made from tensors alone) while the parameters are the same tensors at
the same versions. A compiled call without autograd would redo them in its graph at every call and
guidance pass (a sparse trans_enc guided call: 192 ops, 64 of them matmuls), unless it runs *armed*
(:func:`armed_products`): its wrapper (``runtime/compile.py``) first refreshes every store of the
model in place (same storages: a CUDA graph reads them where they are, no guard changes), and only an
armed trace reads the stores (a trace made elsewhere computes them itself: nothing stale is read).
"""
from __future__ import annotations

import operator
import sys
from contextlib import contextmanager
from typing import Callable, Dict, Iterator, Optional, Sequence, Tuple

import torch
from torch import Tensor, nn

from .attention import compute_dtype
from .structure import structure_version

__all__ = ["ProductStore", "Remade", "armed_products", "products_armed", "refresh_products", "store_of",
           "held_products"]

#: True while a compiled call runs whose model's stores were refreshed for it (read while tracing:
#: Dynamo guards on the value, so an armed and an unarmed trace are two graphs)
_ARMED = [False]
_VERSION = operator.attrgetter("_version")


def products_armed() -> bool:
    """Whether the call being traced (or run) may read :class:`ProductStore` tensors as they are."""
    return _ARMED[0]


@contextmanager
def armed_products(enabled: bool = True) -> Iterator[None]:
    """Within the block, traces read the stores' tensors (the caller refreshed them)."""
    before, _ARMED[0] = _ARMED[0], bool(enabled)
    try:
        yield
    finally:
        _ARMED[0] = before


def _writable_alike(held: Sequence[Tensor], new: Sequence[Tensor]) -> bool:
    """Whether ``new``'s values can be copied into ``held``: the same layouts, and ``held`` not made
    under ``torch.inference_mode`` while this call runs outside it (no in-place write allowed then)."""
    if held and held[0].is_inference() and not torch.is_inference_mode_enabled():
        return False
    return len(held) == len(new) and all(
        (x.shape, x.dtype, x.device, x.stride()) == (y.shape, y.dtype, y.device, y.stride()) for x, y in zip(held, new))


def _none() -> None:
    return None


class Remade:
    """A cache: pickled and deep-copied as None (its owner remakes it on first use, from the copy's own
    tensors; an older version's pickle never meets this version's code)."""

    __slots__ = ()

    def __reduce__(self):
        return (_none, ())


class ProductStore(Remade):
    """Per compute dtype, tensors made from ``inputs`` (parameters, buffers) alone, kept while every
    input is the same tensor at the same version. ``static`` (default): remade values are copied
    into the kept tensors when their layout is unchanged (a graph that reads them needs no new
    capture); else they replace them (a value handed out is never changed afterwards: what a user
    may keep, such as a parametrized weight)."""

    def __init__(self, static: bool = True) -> None:
        self.tensors: Dict[torch.dtype, Tuple[Tensor, ...]] = {}
        self._keys: Dict[torch.dtype, tuple] = {}
        self._unmarked: Dict[torch.dtype, Tuple[Tensor, ...]] = {}   # held, made before Dynamo was loaded
        self.static = static

    def _mark(self, dtype: Optional[torch.dtype] = None, tensors: Tuple[Tensor, ...] = ()) -> None:
        """Tell CUDA graphs that the tensors held for ``dtype`` keep their storage (a captured graph
        reads them in place, no copy per replay); once Dynamo is loaded (importing it costs an eager
        run a second). Until then they wait, the ones replaced dropped (no reference kept to them)."""
        if dtype is not None:
            self._unmarked[dtype] = tensors
        dynamo = sys.modules.get("torch._dynamo")
        if dynamo is not None and hasattr(dynamo, "mark_static_address"):
            for held in self._unmarked.values():
                for t in held:
                    dynamo.mark_static_address(t)
            self._unmarked = {}

    def get(self, dtype: torch.dtype, inputs: Sequence[Tensor], make: Callable[[], Sequence[Tensor]]
            ) -> Tuple[Tensor, ...]:
        """The tensors for ``dtype``, remade by ``make()`` (without autograd) when an input changed."""
        key = (tuple(map(_VERSION, inputs)), tuple(map(Tensor.data_ptr, inputs)))   # (no Python frame per tensor)
        held = self.tensors.get(dtype)
        if held is not None and self._keys.get(dtype) == key:
            if self._unmarked and "torch._dynamo" in sys.modules:
                self._mark()
            return held
        with torch.no_grad():
            if not self.static:
                self.tensors.pop(dtype, None)                 # the old values go before the new are made
                held = None
            new = tuple(make())
            if held is not None and self.static and _writable_alike(held, new):
                for old, value in zip(held, new):
                    old.copy_(value)
            elif self.static:
                inputs_at = set(map(Tensor.data_ptr, inputs))   # own storages: no view, no input's memory
                held = tuple(t.clone() if t._base is not None or t.data_ptr() in inputs_at else t for t in new)
                self._mark(dtype, held)
                self.tensors[dtype] = held
            else:
                held = self.tensors[dtype] = new
        self._keys[dtype] = key
        return held

    def refresh(self, dtype: torch.dtype, inputs: Sequence[Tensor],
                make: Callable[[torch.dtype], Sequence[Tensor]]) -> Tuple[Tensor, ...]:
        """:meth:`get` for ``dtype`` and for every other dtype held (what an armed trace may read),
        ``make(dtype)`` making them; returns ``dtype``'s."""
        if len(self.tensors) > 1 or (self.tensors and dtype not in self.tensors):
            for other in [d for d in self.tensors if d != dtype]:
                self.get(other, inputs, lambda: make(other))
        return self.get(dtype, inputs, lambda: make(dtype))

    def read(self, dtype: torch.dtype) -> Optional[Tuple[Tensor, ...]]:
        """While tracing an armed call: the tensors for ``dtype`` as they are (None when there are
        none, or the call is not armed: the caller computes them)."""
        return self.tensors.get(dtype) if _ARMED[0] else None


def store_of(module: nn.Module, name: str = "_products", static: bool = True) -> ProductStore:
    """``module``'s store ``name`` (made on first use, ``static`` as :class:`ProductStore`'s: a module
    unpickled from an older version has none)."""
    store = module.__dict__.get(name)
    if store is None:
        store = module.__dict__[name] = ProductStore(static)
    return store


def held_products(module: nn.Module, dtype: torch.dtype) -> Optional[Tuple[Tensor, ...]]:
    """While tracing: ``module``'s products for ``dtype`` when the call is armed and it has them, else
    None (no store is made while tracing)."""
    store = module.__dict__.get("_products")
    return None if store is None else store.read(dtype)


class _Holders(Remade):
    """The modules of a model that keep products and every tensor their products are made of, for
    one model structure; ``key``: those tensors' versions and storages (and the compute dtype) at
    the last refresh."""

    __slots__ = ("version", "modules", "inputs", "key")

    def __init__(self, model: nn.Module, version: Optional[int]) -> None:
        self.version = version
        self.modules = [m for m in model.modules() if callable(getattr(type(m), "refresh_products", None))]
        self.inputs = list({id(t): t for m in self.modules for t in m.product_inputs()}.values())
        self.key: Optional[tuple] = None


def refresh_products(model: nn.Module) -> None:
    """Refresh the stores of every module of ``model`` that keeps products (``refresh_products()`` and
    ``product_inputs()`` methods: FSQ attention, Lipschitz MLPs) for the dtype a call computes in
    now. The modules are found once per model structure
    (:func:`~smdm_plugin.core.structure.structure_version`); a call whose inputs are all the same
    tensors at the same versions as at the last refresh, in the same dtype, checks one key."""
    version = structure_version()
    found = model.__dict__.get("_smdm_product_holders")
    if found is None or version is None or found.version != version:
        found = model.__dict__["_smdm_product_holders"] = _Holders(model, version)
    if not found.inputs:
        return
    t = found.inputs
    key = (compute_dtype(t[0]), tuple(map(_VERSION, t)), tuple(map(Tensor.data_ptr, t)))
    if key == found.key:
        return
    for m in found.modules:
        m.refresh_products()
    found.key = key
