"""Lipschitz MLPs with sine activations (sMDM's input/output layers).

Each linear layer carries a learned bound ``softplus(c)`` on its ∞-operator norm (the largest
absolute row sum), enforced by a weight parametrization (Liu et al. 2022, "Learning Smooth Neural
Functions via Lipschitz Regularization")::

    W_hat = W * min(1, softplus(c) / rowsum|W|)        rowsum taken per output row

so ``||W_hat x - W_hat y||_∞ <= softplus(c) ||x - y||_∞``. ``sin(w0 x)`` is ``w0``-Lipschitz
element-wise, hence a :class:`LipschitzMLP` is ``∏ softplus(c_i) · w0^(#sines)``-Lipschitz in the
∞-norm. The training penalty :func:`lipschitz_loss` is ``∏ softplus(c_i)`` (weighted by
``SparseConfig.lipschitz_lambda`` by the caller). :func:`bake_lipschitz` freezes the normalised
weights into plain ``nn.Linear`` weights for inference.
"""
from __future__ import annotations

import math
from typing import List, Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.nn.utils import parametrize

from .checks import compiling as _compiling, module_device

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


def _row_abs_sum(weight: Tensor) -> Tensor:
    """``[out, in] -> [out, 1]``: absolute row sums (each row's contribution to the ∞-norm)."""
    return weight.abs().sum(dim=1, keepdim=True)


class LipschitzWeight(nn.Module):
    """Parametrization ``W -> W * min(1, softplus(c) / rowsum|W|)`` with a learned scalar ``c``.

    ``c`` starts at ``inverse_softplus(max_i rowsum_i|W0|)`` so that the initial weight is (up to
    rounding) unchanged. Rows whose absolute sum is already ``<= softplus(c)`` pass through
    exactly (the scale is clamped to 1).
    """

    def __init__(self, weight: Tensor) -> None:
        super().__init__()
        with torch.no_grad():
            init = _inverse_softplus(_row_abs_sum(weight.detach()).max())
        self.c = nn.Parameter(init.reshape(()).clone())
        self._cache: Optional[Tuple[tuple, Tensor]] = None

    def bound(self) -> Tensor:
        """``softplus(c)``: the layer's ∞-norm bound (scalar, differentiable)."""
        return F.softplus(self.c)

    def forward(self, weight: Tensor) -> Tensor:
        # Without autograd (sampling) the normalised weight only changes when W or c do: reuse it
        # while both are the same tensors at the same version (in-place updates bump the version,
        # a new tensor has a new storage). Never while torch.compile traces.
        # Under autocast the cached weight is kept in autocast's dtype (the value autocast's cast
        # would make at every call: the cached weight is no leaf, autocast would not cache its cast).
        key = None
        if not torch.is_grad_enabled() and not _compiling():
            device = weight.device.type
            dtype = torch.get_autocast_dtype(device) if torch.is_autocast_enabled(device) else weight.dtype
            key = (weight.data_ptr(), weight._version, self.c.data_ptr(), self.c._version,
                   weight.dtype, weight.device, weight.shape, dtype)
            if self._cache is not None and self._cache[0] == key:
                return self._cache[1]
        rowsum = _row_abs_sum(weight).clamp_min(torch.finfo(weight.dtype).eps)  # 0-rows: scale 1
        out = weight * torch.clamp(self.bound() / rowsum, max=1.0)
        if key is not None:
            out = out.to(key[-1])
            self._cache = (key, out)
        return out


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

    @property
    def num_sines(self) -> int:
        return self.num_layers - 1

    @property
    def baked(self) -> bool:
        """True once :func:`bake_lipschitz` removed the parametrizations."""
        return not _lipschitz_layers(self)

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
        return self.net(x)

    def extra_repr(self) -> str:
        return (f"in_features={self.in_features}, out_features={self.out_features}, "
                f"hidden={self.hidden}, layers={self.num_layers}, w0={self.w0}")


def lipschitz_loss(module: nn.Module) -> Tensor:
    """``Σ_MLPs ∏_i softplus(c_i)`` over every (unbaked) :class:`LipschitzMLP` in ``module``.

    A 0-d tensor; ``0.`` on the module's device when there is none. Multiply by
    ``SparseConfig.lipschitz_lambda``.
    """
    groups = [[p.c for p in _lipschitz_layers(m)] for m in module.modules()
              if isinstance(m, LipschitzMLP) and not m.baked]
    groups = [g for g in groups if g]
    if not groups:
        return torch.zeros((), device=module_device(module))
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
