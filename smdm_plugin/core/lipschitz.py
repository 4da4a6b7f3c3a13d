"""Lipschitz MLPs with sine activations (sMDM's input/output layers)."""
from __future__ import annotations

import functools
import math
from contextlib import nullcontext as _nullcontext
from typing import List, Optional, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.nn.utils import parametrize

from .attention import compute_dtype
from .checks import compiling as _compiling, module_device
from .kernels.lipschitz_op import lipschitz_weight, row_abs_sum as _row_abs_sum
from .products import ProductStore, held_products, store_of

#: the per-weight op of eager mode (None: every layer's weights in one pass, as under tracing)
lipschitz_weight_op = lipschitz_weight

#: Lipschitz MLPs as callers hand them over: a module to walk, or the MLPs themselves
MLPs = Union[nn.Module, Sequence["LipschitzMLP"]]

__all__ = [
    "LipschitzWeight",
    "lipschitz_linear",
    "SineActivation",
    "LipschitzMLP",
    "lipschitz_loss",
    "bake_lipschitz",
    "is_lipschitz",
]


def _inverse_softplus(y: Tensor) -> Tensor:
    """``x`` with ``softplus(x) = y`` for ``y > 0`` (stable: ``y + log(1 - exp(-y))``)."""
    y = y.clamp_min(torch.finfo(y.dtype).tiny ** 0.5)
    return y + torch.log(-torch.expm1(-y))


class LipschitzWeight(nn.Module):
    """Parametrization ``W -> W * min(1, softplus(c) / rowsum|W|)`` with a learned scalar ``c``.

    ``c`` starts at ``inverse_softplus(max_i rowsum_i|W0| · (1 + 8ε))`` (``ε``: the weight dtype's
    machine epsilon), so that the initial weight is exactly unchanged: every row's ratio exceeds 1 by
    more than any kernel's rounding. (At ``softplus(c) = max rowsum`` exactly, ``c``'s gradient, which
    only rows with ratio ``<= 1`` carry, would depend on how a kernel rounds the ratio: eager and
    compiled steps disagreed there.) Rows whose absolute sum is ``<= softplus(c)`` pass through
    exactly (the scale is clamped to 1).
    """

    def __init__(self, weight: Tensor) -> None:
        super().__init__()
        with torch.no_grad():
            top = _row_abs_sum(weight.detach()).max().double() * (1 + 8 * torch.finfo(weight.dtype).eps)
            init = _inverse_softplus(top).to(weight.dtype)
        self.c = nn.Parameter(init.reshape(()).clone())

    def bound(self) -> Tensor:
        """``softplus(c)``: the layer's ∞-norm bound (scalar, differentiable)."""
        return F.softplus(self.c)

    def forward(self, weight: Tensor) -> Tensor:
        # Without autograd (sampling) the normalised weight only changes when W or c do: kept in a
        # store (:class:`~smdm_plugin.core.products.ProductStore`, not static: a weight handed out is
        # never changed afterwards) in the dtype it is used in (autocast's: the cached weight is no
        # leaf, autocast would not cache its cast). Never while torch.compile traces.
        if not torch.is_grad_enabled() and not _compiling():
            dtype = compute_dtype(weight)
            return store_of(self, "_kept", static=False).get(
                dtype, (weight, self.c), lambda: (self._normalised(weight).to(dtype),))[0]
        return self._normalised(weight)

    def _normalised(self, weight: Tensor) -> Tensor:
        rowsum = _row_abs_sum(weight).clamp_min(torch.finfo(weight.dtype).eps)  # 0-rows: scale 1
        return weight * torch.clamp(self.bound() / rowsum, max=1.0)


class _NormalisedWeights(torch.autograd.Function):
    """Every :class:`LipschitzWeight` of one MLP in one pass, with autograd: the same values as
    the parametrizations (the same operations, bit for bit), in ``2G + 5`` ops forward
    and ``5G + 10`` backward for ``G`` layers (the parametrizations one by one: about 24 per
    layer). ``row_owner [R]`` long: the layer of each of the ``R`` output rows (all layers' rows
    stacked); inputs ``c_1..c_G, W_1..W_G``; returns ``W_hat_1..W_hat_G``. The backward is written
    out: ``dW = g·scale - sign(W)·r``, ``r = [ratio <= 1][rowsum >= eps]·ratio/rowsum·Σ_j g·W``,
    ``dc = softplus'(c)·Σ_rows [ratio <= 1]/rowsum·Σ_j g·W``."""

    @staticmethod
    def forward(ctx, row_owner: Tensor, *tensors: Tensor):
        G = len(tensors) // 2
        cs, ws = tensors[:G], tensors[G:]
        eps = torch.finfo(ws[0].dtype).eps
        rowsum = torch.cat([_row_abs_sum(w) for w in ws])                  # [R, 1]
        c = torch.stack([t.reshape(()) for t in cs])                          # [G]
        bound = F.softplus(c).index_select(0, row_owner).unsqueeze(1)          # [R, 1]
        # bound / max(rowsum, eps) as the parametrization computes it: the same where rowsum >= eps;
        # below, both ratios exceed 1 (inf for a 0-row), so the scale is 1 either way
        ratio = bound / rowsum
        scale = ratio.clamp(max=1.0)
        sizes = [w.shape[0] for w in ws]
        ctx.sizes, ctx.eps, ctx.c_shapes = sizes, eps, [t.shape for t in cs]
        ctx.save_for_backward(row_owner, c, rowsum, ratio, scale, *ws)
        return tuple(w * sc for w, sc in zip(ws, scale.split(sizes)))

    @staticmethod
    def backward(ctx, *grads: Tensor):
        row_owner, c, rowsum, ratio, scale, *ws = ctx.saved_tensors
        # Σ_j g·W per row as one batched dot product per layer
        gw = torch.cat([torch.bmm(g.unsqueeze(1), w.unsqueeze(2)).view(-1, 1) for g, w in zip(grads, ws)])   # [R, 1]
        # d/d softplus(c), per row: rows with ratio <= 1 have rowsum >= bound > 0 (the others: 0)
        g_bound = torch.where(ratio <= 1.0, gw / rowsum, 0.0)
        r = torch.where(rowsum >= ctx.eps, g_bound * ratio, 0.0)               # -d/d rowsum
        g_c = torch.zeros_like(c).index_add_(0, row_owner, g_bound.squeeze(1))
        g_c = torch.ops.aten.softplus_backward(g_c, c, 1.0, 20.0)
        g_ws = [torch.addcmul(g * sc, torch.sign(w), rr, value=-1.0)
                for g, w, sc, rr in zip(grads, ws, scale.split(ctx.sizes), r.split(ctx.sizes))]
        return (None, *(g_c[i].reshape(shape) for i, shape in enumerate(ctx.c_shapes)), *g_ws)


def normalised_weights(linears: List[nn.Linear], row_owner: Optional[Tensor] = None) -> Optional[List[Tensor]]:
    """The normalised weights of Lipschitz-parametrized ``linears`` (one
    :class:`LipschitzWeight` each, the same dtype), or None when they are not all such layers: in
    eager mode one :func:`~smdm_plugin.core.kernels.lipschitz_op.lipschitz_weight` each; while
    tracing all in one pass (:class:`_NormalisedWeights`: ``2G + 5`` ops forward).
    ``row_owner``: :func:`row_owner` of the layers (a per-device constant the caller keeps), else
    made here."""
    params = []
    for m in linears:
        if not parametrize.is_parametrized(m, "weight") or len(m.parametrizations.weight) != 1:
            return None
        p = m.parametrizations.weight[0]
        if not isinstance(p, LipschitzWeight):
            return None
        params.append((p.c, m.parametrizations.weight.original))
    if len({w.dtype for _, w in params}) != 1:
        return None
    if lipschitz_weight_op is not None and not _compiling():
        return [lipschitz_weight_op(w, c) for c, w in params]            # one op each
    if row_owner is None:
        row_owner = _row_owner([w.shape[0] for _, w in params], params[0][1].device)
    return list(_NormalisedWeights.apply(row_owner, *(c for c, _ in params), *(w for _, w in params)))


def _normalised(pairs: List[Tuple[Tensor, Tensor]], dtype: torch.dtype) -> List[Tensor]:
    """Every ``(W, c)``'s normalised weight in ``dtype``, computed in the weights' own dtype (autocast
    off, as the parametrization computes it)."""
    device = pairs[0][0].device.type
    with torch.autocast(device, enabled=False) if device in ("cpu", "cuda") else _nullcontext():
        return [lipschitz_weight(w, c).to(dtype) for w, c in pairs]


def _row_owner(sizes: List[int], device: torch.device) -> Tensor:
    """``[sum(sizes)]`` long: the layer of every stacked output row (static shapes)."""
    return torch.cat([torch.full((int(n),), i, dtype=torch.long, device=device) for i, n in enumerate(sizes)])


def _siren_uniform_(linear: nn.Linear, bound: float) -> None:
    with torch.no_grad():
        linear.weight.uniform_(-bound, bound)


def lipschitz_linear(in_f: int, out_f: int, bias: bool = True,
                     init_bound: Optional[float] = None,
                     device: Optional[torch.device] = None,
                     dtype: Optional[torch.dtype] = None) -> nn.Linear:
    """``nn.Linear(in_f, out_f)`` whose ``weight`` is parametrized by :class:`LipschitzWeight`.

    ``init_bound``: if given, the raw weight is drawn from ``U(-init_bound, init_bound)`` before
    ``c`` is initialised (otherwise PyTorch's default init is kept).
    """
    linear = nn.Linear(in_f, out_f, bias=bias, device=device, dtype=dtype)
    if init_bound is not None:
        _siren_uniform_(linear, init_bound)
    parametrize.register_parametrization(linear, "weight", LipschitzWeight(linear.weight))
    return linear


class SineActivation(nn.Module):
    """``sin(w0 · x)``, element-wise; ``w0``-Lipschitz. Any shape."""

    def __init__(self, w0: float = 1.0) -> None:
        super().__init__()
        if not w0 > 0:
            raise ValueError(f"SineActivation: w0 must be > 0, got {w0}")
        self.w0 = float(w0)

    def forward(self, x: Tensor) -> Tensor:
        return torch.sin(x if self.w0 == 1.0 else self.w0 * x)     # 1·x is x exactly: one op less

    def extra_repr(self) -> str:
        return f"w0={self.w0}"


def _lipschitz_layers(module: nn.Module) -> List[LipschitzWeight]:
    """The live :class:`LipschitzWeight` parametrizations inside ``module`` (module order)."""
    out = []
    for m in module.modules():
        if parametrize.is_parametrized(m, "weight"):
            out.extend(p for p in m.parametrizations.weight if isinstance(p, LipschitzWeight))
    return out


class LipschitzMLP(nn.Module):
    """``Linear -> Sine -> ... -> Linear`` with Lipschitz-bounded linear layers.

    Shapes: ``[..., in_features] -> [..., out_features]``. ``layers`` linear layers (``>= 1``),
    ``layers - 1`` sine activations (none after the last linear). ``hidden=None`` uses
    ``max(in_features, out_features)``, i.e. the transformer latent width in both the input role
    (features -> latent) and the output role (latent -> features).

    Initialisation (SIREN-like, Sitzmann et al. 2020): every linear layer followed by a sine is
    drawn from ``U(-b, b)`` with ``b = sqrt(3 / (fan_in · v)) / w0`` so that the sine's argument
    ``w0 · Wx`` has about unit variance, where ``v`` is the input's variance: ``v = 1`` for the
    first layer (normalised motion features or transformer latents), ``v = 1/2`` for sine outputs
    (this is SIREN's hidden-layer rule ``sqrt(6 / fan_in) / w0``). The last layer keeps
    PyTorch's default init. Biases keep PyTorch's default init.
    """

    def __init__(self, in_features: int, out_features: int, hidden: Optional[int] = None,
                 layers: int = 2, w0: float = 1.0,
                 device: Optional[torch.device] = None, dtype: Optional[torch.dtype] = None
                 ) -> None:
        super().__init__()
        if int(layers) < 1:
            raise ValueError(f"LipschitzMLP: layers must be >= 1, got {layers}")
        if not w0 > 0:
            raise ValueError(f"LipschitzMLP: w0 must be > 0, got {w0}")
        hidden = int(hidden) if hidden is not None else max(in_features, out_features)
        self.in_features, self.out_features = int(in_features), int(out_features)
        self.hidden, self.num_layers, self.w0 = hidden, int(layers), float(w0)
        widths = [self.in_features] + [hidden] * (self.num_layers - 1) + [self.out_features]
        mods: List[nn.Module] = []
        for i in range(self.num_layers):
            last = i == self.num_layers - 1
            in_var = 1.0 if i == 0 else 0.5
            b = None if last else math.sqrt(3.0 / (widths[i] * in_var)) / self.w0
            mods.append(lipschitz_linear(widths[i], widths[i + 1], init_bound=b,
                                         device=device, dtype=dtype))
            if not last:
                mods.append(SineActivation(self.w0))
        self.net = nn.Sequential(*mods)
        # the layer of every stacked output row (normalised_weights), moved with the module
        self.register_buffer("row_owner", _row_owner(widths[1:], torch.device("cpu")).to(device), persistent=False)

    @property
    def num_sines(self) -> int:
        return self.num_layers - 1

    @property
    def baked(self) -> bool:
        """True once :func:`bake_lipschitz` removed the parametrizations (it removes all of them)."""
        first = self.net[0]
        return not (parametrize.is_parametrized(first, "weight")
                    and isinstance(first.parametrizations.weight[0], LipschitzWeight))

    def lipschitz_product(self) -> Tensor:
        """``∏ softplus(c_i)`` over the linear layers (scalar, differentiable)."""
        cs = [p.bound() for p in _lipschitz_layers(self)]
        if not cs:
            raise RuntimeError("LipschitzMLP.lipschitz_product: module is baked (no c left)")
        return torch.stack(cs).prod()

    def lipschitz_bound(self) -> Tensor:
        """Lipschitz bound in the ∞-norm: ``∏ softplus(c_i) · w0^(#sines)`` (scalar tensor).

        After baking, ``∏ max_row_abs_sum(W_i) · w0^(#sines)`` from the frozen weights (<= the
        bound reported before baking).
        """
        if self.baked:
            prod = torch.stack([_row_abs_sum(m.weight).max() for m in self.net
                                if isinstance(m, nn.Linear)]).prod()
        else:
            prod = self.lipschitz_product()
        return prod * (self.w0 ** self.num_sines)

    def forward(self, x: Tensor) -> Tensor:
        """Every linear layer's normalised weight read without the parametrization's per-access
        machinery: with autograd one op each (:func:`~smdm_plugin.core.kernels.lipschitz_op.lipschitz_weight`;
        while tracing all in one pass, :func:`normalised_weights`), without it kept while unchanged
        (:meth:`_sampling_weights`). The same values as the parametrizations. A contiguous input of
        more than two dimensions runs as its rows ``[-1, in_features]`` (what ``F.linear`` does to
        it in each layer, bit for bit: one view each way for the MLP, not two per layer)."""
        lead = None
        if x.dim() > 2 and x.is_contiguous():
            lead, x = x.shape[:-1], x.view(-1, x.shape[-1])
        x = self._rows(x)
        return x if lead is None else x.view(*lead, x.shape[-1])

    def _rows(self, x: Tensor) -> Tensor:
        pairs = self._weight_pairs()
        if pairs is None:                                            # baked: plain layers
            return self.net(x)
        if not torch.is_grad_enabled():
            weights = self._sampling_weights(x, pairs)
        elif _compiling():
            weights = normalised_weights([m for m in self.net if isinstance(m, nn.Linear)],
                                         self._buffers.get("row_owner"))
        else:
            weights = [lipschitz_weight(w, c) for w, c in pairs]
        if weights is None:
            return self.net(x)
        it = iter(weights)
        for m in self.net:
            if type(m) is SineActivation and not (m._forward_hooks or m._forward_pre_hooks):
                x = m.forward(x)                                     # (no module call: no hooks to run)
            else:
                x = F.linear(x, next(it), m.bias) if isinstance(m, nn.Linear) else m(x)
        return x

    def _weight_pairs(self) -> Optional[List[Tuple[Tensor, Tensor]]]:
        """``(W, c)`` of every linear layer (read from the parametrization's modules directly),
        or None once baked."""
        pairs = []
        for m in self.net:
            if not isinstance(m, nn.Linear):
                continue
            plist = m._modules.get("parametrizations")
            if plist is None:
                return None
            weight = plist._modules["weight"]
            pairs.append((weight._parameters["original"], weight._modules["0"]._parameters["c"]))
        return pairs

    def _sampling_weights(self, x: Tensor, pairs: List[Tuple[Tensor, Tensor]]) -> Optional[List[Tensor]]:
        """Without autograd: every linear layer's normalised weight in the dtype it is used in
        (autocast's, else its own), made once and kept while every weight and ``c`` is the same
        tensor at the same version (:meth:`refresh_products`: a sampling loop normalises once);
        while tracing, those of an armed call (:mod:`~smdm_plugin.core.products`), else None (the
        parametrizations run)."""
        if not _compiling():
            return list(self.refresh_products(pairs))
        held = held_products(self, compute_dtype(pairs[0][0]))
        return None if held is None else list(held)

    def products(self) -> ProductStore:
        """What calls without autograd make from the parameters alone."""
        return store_of(self)

    def product_inputs(self) -> List[Tensor]:
        """Every tensor the normalised weights are made of (:mod:`~smdm_plugin.core.products`)."""
        return [t for pair in self._weight_pairs() or () for t in pair]

    def refresh_products(self, pairs: Optional[List[Tuple[Tensor, Tensor]]] = None) -> Tuple[Tensor, ...]:
        """The normalised weights in the dtype a call computes in now, remade in place when a weight
        or ``c`` changed (with the other dtypes held: :meth:`ProductStore.refresh`); ``()`` once baked."""
        pairs = self._weight_pairs() if pairs is None else pairs
        if pairs is None:
            return ()
        tensors = [t for pair in pairs for t in pair]
        return store_of(self).refresh(compute_dtype(tensors[0]), tensors, functools.partial(_normalised, pairs))

    def extra_repr(self) -> str:
        return (f"in_features={self.in_features}, out_features={self.out_features}, "
                f"hidden={self.hidden}, layers={self.num_layers}, w0={self.w0}")


def lipschitz_mlps(mlps: MLPs) -> List[LipschitzMLP]:
    """The unbaked :class:`LipschitzMLP` of ``mlps``: a module (its submodules, walked), or a
    sequence of MLPs (as a sparse model's state lists them: no walk)."""
    if isinstance(mlps, nn.Module):
        mlps = [m for m in mlps.modules() if isinstance(m, LipschitzMLP)]
    return [m for m in mlps if not m.baked]


def lipschitz_loss(mlps: MLPs) -> Tensor:
    """``Σ_MLPs ∏_i softplus(c_i)`` over every (unbaked) :class:`LipschitzMLP` of ``mlps`` (a
    module, or a sequence of MLPs: :func:`lipschitz_mlps`).

    A 0-d tensor; ``0.`` on the module's device when there is none. Multiply by
    ``SparseConfig.lipschitz_lambda``.
    """
    groups = [[p.c for p in _lipschitz_layers(m)] for m in lipschitz_mlps(mlps)]
    groups = [g for g in groups if g]
    if not groups:
        device = module_device(mlps) if isinstance(mlps, nn.Module) else torch.device("cpu")
        return torch.zeros((), device=device)
    # one softplus over every c; per-MLP products by log-sum (softplus(c) > 0); a few ops, whatever
    # the number of layers
    log_b = torch.log(F.softplus(torch.stack([c.reshape(()) for g in groups for c in g])))
    sizes = [len(g) for g in groups]
    if len(set(sizes)) == 1:
        return torch.exp(log_b.view(len(groups), -1).sum(1)).sum()
    starts = [sum(sizes[:i]) for i in range(len(sizes))]
    return torch.stack([torch.exp(log_b[a:a + n].sum()) for a, n in zip(starts, sizes)]).sum()


def bake_lipschitz(module: nn.Module) -> nn.Module:
    """In place: replace every Lipschitz-parametrized weight by its current normalised value.

    The layers become plain ``nn.Linear`` (state-dict key ``...weight`` instead of
    ``...parametrizations.weight.original`` / ``...parametrizations.weight.0.c``); outputs are
    unchanged. Returns ``module``.
    """
    for m in list(module.modules()):
        if parametrize.is_parametrized(m, "weight") and any(
                isinstance(p, LipschitzWeight) for p in m.parametrizations.weight):
            with torch.autocast(m.parametrizations.weight.original.device.type, enabled=False):
                parametrize.remove_parametrizations(m, "weight", leave_parametrized=True)   # its own dtype
    return module


def is_lipschitz(module: nn.Module) -> bool:
    """True when ``module`` (or a submodule) has a live :class:`LipschitzWeight`
    parametrization, i.e. it is trainable-Lipschitz and not yet baked."""
    return bool(_lipschitz_layers(module))
