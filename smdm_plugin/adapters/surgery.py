"""``sparsify`` / ``unsparsify`` for every registered model family (PEFT-style, in place, reversible).

No wrapper class: the model keeps its type and attributes. The model's
:class:`~smdm_plugin.adapters.family.ModelFamily` says which layers change; the steps are the same
for all: Lipschitz sine MLPs in place of the input/output linears (``config.lipschitz``), the
family's keyframe-only blocks and hooks, a persistent buffer ``smdm_sparse_version`` marking the
state dict as sparse, one :class:`~smdm_plugin.adapters.state.SparseState` as ``model._smdm_state``.

``sparsify`` is transactional: the new modules are built first and every replacement is recorded
before it is made, so on any error the model is exactly as before (same module objects, no hook,
no buffer, no state) and a corrected retry works.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Dict, Mapping, Tuple, Union

import torch
import torch.nn as nn

from ..core.checks import module_device
from ..core.config import MARKER, SparseConfig
from ..core.lipschitz import LipschitzMLP
from ..core.noise import NOISE_STEP, NOISE_TABLE
from ..core.schedule import MaskSchedule
from .diffusion_wrapper import attach_diffusion, diffusion_steps, release_diffusions
from .families import family_for, get_family
from .family import ModelFamily
from .state import STATE_ATTR, SparseState, get_state, restore_originals

ConfigLike = Union[SparseConfig, Mapping[str, Any], None]


def as_config(config: ConfigLike, fn: str = "sparsify") -> SparseConfig:
    """``config`` as a validated :class:`SparseConfig`: None = the defaults; a mapping of field names
    is converted (unknown names or bad values are a ``ValueError``); anything else a ``TypeError``."""
    if config is None:
        return SparseConfig()
    if isinstance(config, SparseConfig):
        return dataclasses.replace(config)     # checked again (a field set after it was built), the caller's untouched
    if isinstance(config, Mapping):
        return SparseConfig.from_dict(config)
    raise TypeError(f"{fn}: config must be a SparseConfig, a dict of its fields or None, "
                    f"got {type(config).__name__}")


def model_device(model: nn.Module, fn: str = "sparsify") -> torch.device:
    """The device of ``model``'s parameters (CPU when it has none); the ``meta`` device is a
    ``ValueError`` (materialise the weights first: ``to_empty`` + ``load_state_dict``)."""
    device = module_device(model)
    if device.type == "meta":
        raise ValueError(f"{fn}: the model's parameters are on the 'meta' device; materialise them "
                         "(model.to_empty(device=...) and load the weights) before converting it")
    return device


def _check_stats(name: str, value: Any, device: torch.device, fn: str) -> None:
    """Dataset statistics may be host data (numpy, lists, CPU tensors) or tensors on the model's
    device, of real finite numbers; ``meta`` tensors, another accelerator, NaN / inf (which would
    silently change which frames are keyframes), complex or non-numeric values are a ``ValueError``."""
    if value is None:
        return
    if isinstance(value, torch.Tensor):
        if value.device.type == "meta":
            raise ValueError(f"{fn}: {name} is a 'meta' tensor (no values); pass the [D] statistics as data")
        if value.device.type != "cpu" and value.device != device:
            raise ValueError(f"{fn}: {name} is on {value.device} but the model is on {device}; pass it on "
                             f"the CPU or on {device}")
        t = value.detach()
    else:
        try:
            t = torch.as_tensor(value)
        except (TypeError, ValueError, RuntimeError) as e:
            raise ValueError(f"{fn}: {name} must be [D] real numbers, got {type(value).__name__} ({e})") from None
    if t.is_complex() or t.dtype == torch.bool:
        raise ValueError(f"{fn}: {name} must be [D] real numbers, got dtype {t.dtype}")
    if t.dim() != 1 or not t.numel():
        raise ValueError(f"{fn}: {name} must be [D] (one value per motion feature), got shape {tuple(t.shape)}")
    if t.is_floating_point() and not bool(torch.isfinite(t).all()):  # once, at conversion: not the hot path
        bad = int(torch.nonzero(~torch.isfinite(t.reshape(-1)))[0])
        raise ValueError(f"{fn}: {name} holds a non-finite value ({float(t.reshape(-1)[bad])} at index {bad}); "
                         "the [D] statistics must be finite")


def _check_stats_pair(mean: Any, std: Any, device: torch.device, fn: str) -> None:
    """:func:`_check_stats` of both, and ``[D]`` both when both are given."""
    _check_stats("mean", mean, device, fn)
    _check_stats("std", std, device, fn)
    if mean is not None and std is not None and len(mean) != len(std):
        raise ValueError(f"{fn}: mean and std must both be [D], got {len(mean)} and {len(std)} values")


def _module(model: Any, fn: str) -> nn.Module:
    """``model``, an ``nn.Module``, else a ``TypeError`` naming ``fn``."""
    if not isinstance(model, nn.Module):
        raise TypeError(f"{fn}: model must be a torch.nn.Module, got {type(model).__name__}")
    return model


def is_sparse(model: nn.Module) -> bool:
    """Whether ``model`` itself was sparsified (see :func:`sparsify`)."""
    return get_state(_module(model, "is_sparse")) is not None


def _lipschitz_layers(family: ModelFamily, model: nn.Module, config: SparseConfig
                      ) -> Dict[Tuple[nn.Module, str], nn.Module]:
    """The new Lipschitz MLPs, built (not installed): ``(owner, attribute) -> MLP``."""
    new: Dict[Tuple[nn.Module, str], nn.Module] = {}
    hidden = config.lipschitz_hidden or family.latent_dim(model)
    for owner, name in family.io_layers(model):
        old = getattr(owner, name, None)
        if not isinstance(old, nn.Linear):
            continue
        mlp = LipschitzMLP(old.in_features, old.out_features, hidden=hidden,
                           layers=config.lipschitz_layers, w0=config.sine_w0)
        new[(owner, name)] = mlp.to(device=old.weight.device, dtype=old.weight.dtype)
    return new


def sparsify(model: nn.Module, config: ConfigLike = None, *, diffusion: Any = None,
             mean: Any = None, std: Any = None, family: Union[str, ModelFamily, None] = None) -> nn.Module:
    """Convert ``model`` to sparse keyframe mode in place and return it.

    Args:
        model: a model of a registered family (MDM trans_enc / trans_dec, DiP, priorMDM
            doubleTake_MDM, MotionDiffuse's MotionTransformer, the in-package ``TinyMDM``).
        config: a :class:`SparseConfig` or a dict of its fields; ``enabled=False`` returns ``model``
            untouched.
        diffusion: if given, its ``training_losses`` is wrapped (:func:`attach_diffusion`) so that
            training keyframes come from x0 and ``lipschitz_lambda * L_lip`` joins the loss; its
            step count becomes ``config.diffusion_steps``.
        mean, std: ``[D]`` dataset statistics used to de-normalise motions for VW (HumanML3D/KIT).
        family: the family's name or object; None = the first registered family that matches.
    """
    _module(model, "sparsify")
    config = as_config(config)
    if family is not None and not isinstance(family, (str, ModelFamily)):
        raise TypeError(f"sparsify: family must be a family name or a ModelFamily, got {type(family).__name__}")
    if not config.enabled:
        return model
    if is_sparse(model):
        raise ValueError(f"sparsify: {type(model).__name__} is already sparse (unsparsify it first)")
    fam = (get_family(family) if isinstance(family, str) else family) if family is not None else family_for(model)
    if family is not None and not fam.matches(model):
        raise TypeError(f"sparsify: {type(model).__name__} is not a {fam.name} model: {fam.mismatch(model)}")
    device = model_device(model)
    if diffusion is not None and not callable(getattr(diffusion, "training_losses", None)):  # step count: below
        raise TypeError(f"sparsify: diffusion must be a Gaussian diffusion with a callable training_losses(model, "
                        "x_start, t, model_kwargs) and its step count (num_timesteps or original_num_steps), got "
                        f"{type(diffusion).__name__}")
    _check_stats_pair(mean, std, device, "sparsify")
    variant = fam.variant(model)
    if diffusion is not None:
        config = config.replace(diffusion_steps=diffusion_steps(diffusion))
    config = fam.prepare_config(model, config, variant)
    schedule = MaskSchedule(config, mean, std)
    lipschitz = _lipschitz_layers(fam, model, config) if config.lipschitz else {}
    state = SparseState(config=config, variant=variant, schedule=schedule, family=fam,
                        lipschitz_mlps=list(lipschitz.values()))
    try:                                               # swap: every change recorded before it is made
        for (owner, name), mlp in lipschitz.items():
            state.originals[(owner, name)] = getattr(owner, name)
            setattr(owner, name, mlp)
        fam.install(model, state)
        model.register_buffer(MARKER, torch.tensor(config.version, device=device), persistent=True)
        model.register_buffer(NOISE_STEP, torch.zeros((), dtype=torch.long, device=device), persistent=True)
        if schedule.noise_table is not None:           # on the model: moves with it, made before tracing
            model.register_buffer(NOISE_TABLE, schedule.noise_table.view(torch.int32).to(device), persistent=False)
        register = getattr(model, "register_load_state_dict_pre_hook", None)   # public since torch 2.3
        state.handles.append(register(_keep_noise_step) if register is not None
                             else model._register_load_state_dict_pre_hook(_keep_noise_step, with_module=True))
        setattr(model, STATE_ATTR, state)
        if diffusion is not None:
            attach_diffusion(diffusion, model=model)
    except BaseException:
        _undo(model, state, rollback=True)
        raise
    return model


def _undo(model: nn.Module, state: SparseState, rollback: bool = False) -> None:
    """Everything :func:`sparsify` did, undone: ``unsparsify`` (the family carries trained weights
    into what is restored) or ``rollback`` after a failure part-way (the original objects back)."""
    if get_state(model) is state:
        release_diffusions(model)
    for h in state.handles:
        h.remove()
    state.handles.clear()
    if not rollback:
        state.family.uninstall(model, state)
    restore_originals(state.originals)
    state.originals.clear()
    model._buffers.pop(MARKER, None)
    model._buffers.pop(NOISE_STEP, None)
    model._buffers.pop(NOISE_TABLE, None)
    model.__dict__.pop(STATE_ATTR, None)


def _keep_noise_step(module: nn.Module, state_dict: Dict[str, Any], prefix: str, *args: Any) -> None:
    """A state dict without the mask-noise step (written before it existed, or a dense one) loads
    as before: the model keeps its own step."""
    key = prefix + NOISE_STEP
    if key not in state_dict and NOISE_STEP in module._buffers:
        state_dict[key] = module._buffers[NOISE_STEP]


def unsparsify(model: nn.Module) -> nn.Module:
    """Undo :func:`sparsify`: the original dense layers back, hooks removed, the diffusions it was
    attached to restored (when no other sparse model uses them).

    The dense input/output layers come back with the weights they had when the model was
    sparsified; weights learned in sparse mode by the Lipschitz MLPs are dropped (they have no
    dense equivalent). Family-specific changes with a dense equivalent keep their trained weights
    (MDM: FSQ self-attention becomes ``nn.MultiheadAttention`` with its current q/k/v/out weights).
    """
    state = get_state(_module(model, "unsparsify"))
    if state is None:
        return model
    _undo(model, state)
    return model


def set_mean_std(model: nn.Module, mean: Any, std: Any) -> None:
    """Give a sparse model the dataset Mean/Std after the fact (e.g. once the data is loaded)."""
    state = get_state(_module(model, "set_mean_std"))
    if state is None:
        raise ValueError(f"set_mean_std: {type(model).__name__} is not sparse (sparsify it first)")
    device = model_device(model, "set_mean_std")
    _check_stats_pair(mean, std, device, "set_mean_std")
    state.schedule = MaskSchedule(state.config, mean, std, noise_seed=state.schedule.noise_seed)
