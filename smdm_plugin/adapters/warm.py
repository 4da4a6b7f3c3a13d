"""Start sparse from a dense checkpoint: the zero-shot wrap and the warm start.

* :func:`wrap_dense` — sparse sampling of a dense model with every trained weight as it is: a
  config that adds no layer (``lipschitz=False, fsq=False``; preset ``zero_shot``), and the model
  accepts dense state dicts (the sparse marker is filled in when a dense one is loaded).
* :func:`warm_start` — sparse training initialised from a dense model: the transformer keeps its
  weights; the recipe's new layers are initialised to reproduce the dense ones on the model's own
  inputs (``probe``): each Lipschitz sine MLP is built to equal the dense input/output linear up to
  the sine's curvature (:func:`fit_mlp_to_linear`), each FSQ key projection from a PCA of the dense
  keys with a least-squares ``key_up`` (:func:`fit_fsq_to_keys`). The measured errors come back in
  a :class:`WarmStartReport`.
"""
from __future__ import annotations

import hashlib
import math
import weakref
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Dict, List, Optional, Tuple, Union

import torch
import torch.nn as nn
from torch.nn.utils import parametrize

from ..core.config import MARKER, SparseConfig
from ..core.presets import load_preset
from ..core.fsq import FSQMultiheadAttention
from ..core.lipschitz import LipschitzMLP, LipschitzWeight
from .families import family_for, get_family
from .state import get_state

__all__ = ["ZERO_SHOT_PRESET", "adds_layers", "wrap_dense", "is_dense_wrap", "file_digest", "FitError",
           "WarmStartReport", "fit_mlp_to_linear", "fit_fsq_to_keys", "warm_start", "diffusion_probe"]

#: the packaged preset of the zero-shot wrap (configs/zero_shot.yaml)
ZERO_SHOT_PRESET = "zero_shot"

ConfigOrPreset = Union[SparseConfig, str, None]

#: models wrapped by :func:`wrap_dense` -> where their dense weights came from (None: not said)
_WRAPPED: "weakref.WeakKeyDictionary[nn.Module, Optional[str]]" = weakref.WeakKeyDictionary()


def _config(config: ConfigOrPreset, fn: str) -> SparseConfig:
    if config is None:
        return load_preset(ZERO_SHOT_PRESET)
    if isinstance(config, str):
        return load_preset(config)
    if isinstance(config, SparseConfig):
        return config
    raise TypeError(f"{fn}: config must be a SparseConfig, a preset name/path or None, got {type(config).__name__}")


def adds_layers(config: SparseConfig) -> bool:
    """Whether sparsifying with ``config`` adds layers a dense checkpoint has no weights for
    (Lipschitz sine MLPs, FSQ key projections)."""
    return bool(config.lipschitz or config.fsq)


def _fill_marker(module: nn.Module, state_dict: Dict[str, Any], prefix: str, *args: Any) -> None:
    """Load-state-dict pre-hook of a wrapped model: a dense state dict loads (marker filled in)."""
    key = prefix + MARKER
    if key not in state_dict and MARKER in module._buffers:
        state_dict[key] = module._buffers[MARKER]


def wrap_dense(model: nn.Module, config: ConfigOrPreset = None, *, diffusion: Any = None, mean: Any = None,
               std: Any = None, family: Any = None, origin: Optional[str] = None) -> nn.Module:
    """Sparse sampling of a dense model, every trained weight kept (in place; returns ``model``).

    ``config``: a :class:`SparseConfig` or a preset (default ``zero_shot``) that adds no layer
    (``lipschitz`` and ``fsq`` off; otherwise ``ValueError``: those layers would be untrained).
    The model then loads dense state dicts as well as its own (the upstream loaders call
    ``load_state_dict`` after building the model). ``origin`` (e.g. the checkpoint path) is kept
    for :func:`is_dense_wrap`'s callers to report. Undo with ``unsparsify``."""
    from .surgery import sparsify

    config = _config(config, "wrap_dense")
    if not config.enabled:
        raise ValueError("wrap_dense: config.enabled is false (nothing to wrap)")
    if adds_layers(config):
        raise ValueError(f"wrap_dense: config adds layers a dense checkpoint has no weights for (lipschitz="
                         f"{config.lipschitz}, fsq={config.fsq}); use the preset {ZERO_SHOT_PRESET!r} (both off), "
                         "or warm_start() to train them")
    sparsify(model, config, diffusion=diffusion, mean=mean, std=std, family=family)
    state = get_state(model)
    register = getattr(model, "register_load_state_dict_pre_hook", None)
    state.handles.append(register(_fill_marker) if register is not None
                         else model._register_load_state_dict_pre_hook(_fill_marker, with_module=True))
    _WRAPPED[model] = origin
    return model


def is_dense_wrap(model: nn.Module) -> bool:
    """Whether ``model`` is sparse through :func:`wrap_dense` (and not unsparsified since)."""
    return get_state(model) is not None and model in _WRAPPED


def file_digest(path: str) -> str:
    """``sha256:<hex>`` of a file's bytes (the dense origin's content digest)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return "sha256:" + h.hexdigest()


# ------------------------------------------------------------------------------------ warm start
@dataclass
class FitError:
    """How well a new layer reproduces its dense counterpart on the probe's inputs: ``rel_rms``
    (RMS of the difference / RMS of the dense output) and ``max_abs`` (largest absolute
    difference), ``rows`` inputs."""

    layer: str
    rel_rms: float
    max_abs: float
    rows: int


@dataclass
class WarmStartReport:
    """What :func:`warm_start` did: the fits of the Lipschitz MLPs and the FSQ key projections."""

    mlps: List[FitError] = field(default_factory=list)
    fsq: List[FitError] = field(default_factory=list)

    def to_dict(self) -> Dict[str, Any]:
        return {"mlps": [asdict(e) for e in self.mlps], "fsq": [asdict(e) for e in self.fsq]}

    def summary(self) -> str:
        parts = []
        for name, errs in (("Lipschitz MLPs", self.mlps), ("FSQ keys", self.fsq)):
            if errs:
                parts.append(f"{name}: relative RMS error " + ", ".join(f"{e.layer} {e.rel_rms:.2e}" for e in errs))
        return "; ".join(parts) or "no new layers"


def _error(name: str, got: torch.Tensor, want: torch.Tensor) -> FitError:
    d = (got - want).double()
    rms = float(want.double().pow(2).mean().sqrt())
    return FitError(name, float(d.pow(2).mean().sqrt()) / max(rms, 1e-30), float(d.abs().max()), int(want.shape[0]))


def _set_lipschitz(linear: nn.Linear, weight: torch.Tensor, bias: torch.Tensor) -> None:
    """Set a Lipschitz-parametrized linear's raw weight and bias, its bound ``c`` to the new
    weight's largest row sum (the parametrization then passes the weight through unchanged)."""
    with torch.no_grad():
        if parametrize.is_parametrized(linear, "weight"):
            linear.parametrizations.weight.original.copy_(weight)
            for p in linear.parametrizations.weight:
                if isinstance(p, LipschitzWeight):
                    y = weight.abs().sum(1).max().clamp_min(1e-12) * 1.0001
                    p.c.copy_(y + torch.log(-torch.expm1(-y)))   # inverse softplus
        else:
            linear.weight.copy_(weight)
        if linear.bias is not None:
            linear.bias.copy_(bias)


def fit_mlp_to_linear(mlp: LipschitzMLP, linear: nn.Linear, inputs: torch.Tensor, amplitude: float = 0.05,
                      name: str = "layer") -> FitError:
    """Make ``mlp`` (``Linear -> sin -> ... -> Linear``) equal ``linear`` on ``inputs [M, in]``.

    Closed form: the first layer maps ``x`` to a small multiple ``eps * P x`` (``sin(z) ~ z`` there),
    hidden layers pass it on, the last layer multiplies by ``1/eps`` and applies the rest of the
    dense map. ``P`` is the identity when ``hidden >= in``, else the dense weight itself when
    ``hidden >= out``, else its top-``hidden`` singular directions. ``eps`` puts the largest
    first-layer pre-activation at ``amplitude`` radians (the sine's relative error is at most about
    ``amplitude^2 / 6``); with more input rows than hidden units the last layer is then refitted by
    least squares on ``inputs``. A small ``amplitude`` is exact but gives small first-layer weights,
    which an optimiser's fixed step (Adam) moves relatively more. Returns the measured error on ``inputs``."""
    W, b = linear.weight.detach().double(), (linear.bias.detach().double() if linear.bias is not None
                                             else torch.zeros(linear.out_features, dtype=torch.float64,
                                                              device=linear.weight.device))
    lins = [m for m in mlp.net if isinstance(m, nn.Linear)]
    H, n_in, n_out, w0 = mlp.hidden, linear.in_features, linear.out_features, mlp.w0
    x = inputs.detach().reshape(-1, n_in).double()
    if len(lins) == 1:                                   # no sine: the linear itself
        _set_lipschitz(lins[0], W.to(lins[0].weight.dtype), b.to(lins[0].weight.dtype))
    else:
        dev = W.device
        if H >= n_in:
            P, Pb, Q, Qb = torch.eye(H, n_in, dtype=W.dtype, device=dev), torch.zeros(H, dtype=W.dtype, device=dev), \
                torch.cat([W, W.new_zeros(n_out, H - n_in)], 1), b
        elif H >= n_out:
            P, Pb = torch.cat([W, W.new_zeros(H - n_out, n_in)], 0), torch.cat([b, b.new_zeros(H - n_out)])
            Q, Qb = torch.eye(n_out, H, dtype=W.dtype, device=dev), torch.zeros_like(b)
        else:
            U, S, Vh = torch.linalg.svd(W, full_matrices=False)
            P, Pb = Vh[:H], torch.zeros(H, dtype=W.dtype, device=dev)
            Q, Qb = U[:, :H] * S[:H], b
        z = x @ P.T + Pb if x.numel() else x.new_zeros(1, H)
        eps = amplitude / max(float(z.abs().max()), 1e-12)
        dt = lins[0].weight.dtype
        _set_lipschitz(lins[0], (eps / w0 * P).to(dt), (eps / w0 * Pb).to(dt))
        for mid in lins[1:-1]:                           # sin(w0 * (I / w0) h) ~ h
            eye = (torch.eye(H, dtype=W.dtype, device=dev) / w0).to(dt)
            _set_lipschitz(mid, eye, torch.zeros(H, device=dev, dtype=dt))
        _set_lipschitz(lins[-1], (Q / eps).to(dt), Qb.to(dt))
        if x.shape[0] > H:                               # then the last layer by least squares on the inputs
            with torch.no_grad():
                h = mlp.net[:-1](x.to(dt)).double()
                A = torch.cat([h, h.new_ones(h.shape[0], 1)], 1).cpu()
                target = (x @ W.T + b).cpu()
                sol = torch.linalg.lstsq(A, target, driver="gelsd").solution.to(dev)   # [H + 1, out]
            _set_lipschitz(lins[-1], sol[:H].T.contiguous().to(dt), sol[H].to(dt))
    with torch.no_grad():
        xs = inputs.detach().reshape(-1, n_in)
        return _error(name, mlp(xs), linear(xs))


def fit_fsq_to_keys(attn: FSQMultiheadAttention, keys: torch.Tensor, spread: float = 0.8,
                    name: str = "attn") -> FitError:
    """Initialise ``attn``'s key codebook projections from dense keys ``keys [M, head_dim]`` (the
    in-projection's keys of every head): ``key_down`` = the top-``d`` principal directions, each
    scaled so that one standard deviation lands at ``spread`` of tanh's range, then ``key_up``
    (weight and bias) = the least-squares map from the quantised codes back to the keys. Returns
    the reconstruction error of the keys."""
    k = keys.detach().reshape(-1, attn.head_dim).double()
    d = attn.fsq.dim
    mu = k.mean(0)
    U, S, Vh = torch.linalg.svd(k - mu, full_matrices=False)
    sd = (S[:d] / math.sqrt(max(k.shape[0] - 1, 1))).clamp_min(1e-8)
    down = spread * Vh[:d] / sd[:, None]                               # [d, head_dim]
    dt = attn.key_down.weight.dtype
    with torch.no_grad():
        attn.key_down.weight.copy_(down.to(dt))
        attn.key_down.bias.copy_((-(down @ mu)).to(dt))
        codes = attn.fsq(attn.key_down(k.to(dt))).double()            # [M, d] in [-1, 1]
        A = torch.cat([codes, codes.new_ones(codes.shape[0], 1)], 1)
        sol = torch.linalg.lstsq(A.cpu(), k.cpu()).solution.to(k.device)  # [d + 1, head_dim]
        attn.key_up.weight.copy_(sol[:d].T.to(dt))
        attn.key_up.bias.copy_(sol[d].to(dt))
        rec = attn.key_up(attn.fsq(attn.key_down(k.to(dt))))
    return _error(name, rec.double(), k)


def diffusion_probe(x0: torch.Tensor, model_kwargs: Dict[str, Any], q_sample: Callable[..., torch.Tensor],
                    num_timesteps: int, seed: int = 0, steps: int = 4) -> Callable[[nn.Module], None]:
    """A probe for :func:`warm_start`: the model run on noised data ``q_sample(x0, t, noise)`` at
    ``steps`` diffusion steps spread over ``[0, num_timesteps)`` (a private generator: the global
    random stream is not touched). ``x0 [B, D, 1, N]``."""
    def run(model: nn.Module) -> None:
        g = torch.Generator(device=x0.device).manual_seed(seed)
        for i in range(steps):
            t = torch.full((x0.shape[0],), int((i + 0.5) * num_timesteps / steps), device=x0.device, dtype=torch.long)
            noise = torch.randn(x0.shape, generator=g, device=x0.device, dtype=x0.dtype)
            model(q_sample(x0, t, noise=noise), t, **model_kwargs)
    return run


Recorded = Dict[str, List[torch.Tensor]]


def _record(model: nn.Module, layers: List[Tuple[str, nn.Module]], probe: Callable[[nn.Module], None],
            key_of: Callable[[tuple, dict], torch.Tensor]) -> Tuple[Recorded, Recorded]:
    """Run ``probe(model)`` in eval mode (gradients on: no fused fast path that skips the hooks),
    recording the inputs of the io linears and the key inputs of the self-attentions."""
    lin_in: Dict[str, List[torch.Tensor]] = {n: [] for n, m in layers if isinstance(m, nn.Linear)}
    key_in: Dict[str, List[torch.Tensor]] = {n: [] for n, m in layers if isinstance(m, nn.MultiheadAttention)}
    handles = []
    for n, m in layers:
        if n in lin_in:
            handles.append(m.register_forward_pre_hook(lambda mod, a, n=n: lin_in[n].append(a[0].detach())))
        elif n in key_in:
            handles.append(m.register_forward_pre_hook(
                lambda mod, a, kw, n=n: key_in[n].append(key_of(a, kw).detach()), with_kwargs=True))
    was_training = model.training
    try:
        model.eval()
        with torch.enable_grad():
            probe(model)
    finally:
        model.train(was_training)
        for h in handles:
            h.remove()
    return lin_in, key_in


def _key_arg(args: tuple, kwargs: dict) -> torch.Tensor:
    return args[1] if len(args) > 1 else kwargs["key"]


def warm_start(model: nn.Module, config: ConfigOrPreset, probe: Callable[[nn.Module], None], *,
               diffusion: Any = None, mean: Any = None, std: Any = None, family: Any = None,
               amplitude: float = 0.05) -> WarmStartReport:
    """Sparsify a dense ``model`` holding trained weights, with the recipe's new layers initialised
    to reproduce the dense ones (in place).

    ``probe(model)`` runs the dense model on representative inputs (:func:`diffusion_probe`: noised
    training motions); the inputs of the dense input/output linears and the keys of every
    self-attention are recorded, then ``sparsify(model, config, ...)`` and: each Lipschitz MLP is
    set by :func:`fit_mlp_to_linear` to its dense linear, each FSQ attention's key projections by
    :func:`fit_fsq_to_keys`. Returns the measured errors."""
    from .surgery import sparsify

    config = _config(config, "warm_start")
    fam = (get_family(family) if isinstance(family, str) else family) if family is not None else family_for(model)
    io = [(f"{type(owner).__name__}.{name}", owner, name) for owner, name in fam.io_layers(model)
          if isinstance(getattr(owner, name, None), nn.Linear)]
    dense_linears = {label: getattr(owner, name) for label, owner, name in io}
    attns = [(f"self_attn[{i}]", m.self_attn) for i, m in enumerate(
        mod for mod in model.modules() if isinstance(getattr(mod, "self_attn", None), nn.MultiheadAttention))]
    need = [(label, lin) for label, lin in dense_linears.items()] if config.lipschitz else []
    need += attns if config.fsq else []
    lin_in, key_in = _record(model, need, probe, _key_arg) if need else ({}, {})
    attn_ids = [id(a) for _, a in attns]
    sparsify(model, config, diffusion=diffusion, mean=mean, std=std, family=fam)
    report = WarmStartReport()
    for label, owner, name in io:
        mlp = getattr(owner, name)
        if isinstance(mlp, LipschitzMLP) and lin_in.get(label):
            x = torch.cat([t.reshape(-1, mlp.in_features) for t in lin_in[label]])
            report.mlps.append(fit_mlp_to_linear(mlp, dense_linears[label], x, amplitude, label))
    if config.fsq:
        state = get_state(model)
        fsq_by_old = {id(old): getattr(owner, n) for (owner, n), old in state.originals.items() if n == "self_attn"}
        for (label, old), oid in zip(attns, attn_ids):
            new = fsq_by_old.get(oid)
            if not isinstance(new, FSQMultiheadAttention) or not key_in.get(label):
                continue
            E = old.embed_dim
            w, bias = old.in_proj_weight[E:2 * E].detach(), (old.in_proj_bias[E:2 * E].detach()
                                                            if old.in_proj_bias is not None else None)
            kin = torch.cat([t.reshape(-1, E) for t in key_in[label]])
            with torch.no_grad():
                k = torch.nn.functional.linear(kin, w, bias).reshape(-1, new.head_dim)
            report.fsq.append(fit_fsq_to_keys(new, k, name=label))
    return report
