"""``sparsify``: turn an MDM-family model (MDM trans_enc / trans_dec, DiP, priorMDM's
doubleTake_MDM, the in-package ``TinyMDM``) into its sparse keyframe version, in place.

No wrapper class: the model keeps its type and attributes (``rot2xyz``, ``njoints``,
``parameters_wo_clip()``...). What changes:

* ``input_process.poseEmbedding`` / ``output_process.poseFinal`` (and ``velEmbedding`` /
  ``velFinal`` when present) become Lipschitz sine MLPs (``config.lipschitz``);
* ``seqTransEncoder`` / ``seqTransDecoder`` is wrapped by :class:`KeyframeTransformer` (and its
  self-attention keys FSQ-quantised with ``config.fsq``);
* a forward pre-hook decides the keyframes of every call and builds its
  :class:`~smdm_plugin.core.plan.KeyframePlan` once: ``y['keyframe_mask']`` when given (training:
  the diffusion wrapper selects it from x0 and passes its capacity as ``y['keyframe_capacity']``),
  else the sampling schedule on ``(x_t, timesteps)``; ``y['keyframe_forced']`` frames are always
  keyframes (inside the budget); DiP's ``context_len`` prefix frames are always kept. The input
  embedding, the keyframe transformer and the interpolation all read that one plan;
* a persistent buffer ``smdm_sparse_version`` marks the state dict as sparse.

A call has static shapes and no host synchronisation (unless forced keyframes live on an
accelerator: their count is read once to size the plan), so ``torch.compile(model,
fullgraph=True)`` and CUDA graphs work on the sparse model as on the dense one.
"""
from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import torch
import torch.nn as nn

from ..core.attention_backends import gather_rows, scatter_rows
from ..core.checks import host_checkable
from ..core.config import MARKER, SparseConfig
from ..core.fsq import quantize_attention_keys, unquantize_attention_keys
from ..core.interpolation import interpolate_keyframes_cubic
from ..core.keyframe_transformer import KeyframeTransformer
from ..core.lipschitz import LipschitzMLP
from ..core.plan import KeyframePlan
from ..core.schedule import MaskSchedule
from .diffusion import attach_diffusion, diffusion_steps, release_diffusions
from .state import (STATE_ATTR, SparseState, Variant, forced_from_y, frames_layout, get_state,
                    lengths_from_y, protected_count)

_TRANSFORMERS = ("seqTransEncoder", "seqTransDecoder")


def detect_variant(model: nn.Module) -> Variant:
    """Recognise an MDM-family model by its structure; a clear error lists what is missing."""
    required = ["input_process", "output_process", "arch"]
    missing = [a for a in required if not hasattr(model, a)]
    if not missing:
        if not hasattr(model.input_process, "poseEmbedding"):
            missing.append("input_process.poseEmbedding")
        if not hasattr(model.output_process, "poseFinal"):
            missing.append("output_process.poseFinal")
    if missing:
        raise TypeError(f"sparsify: {type(model).__name__} is not an MDM-family model; missing "
                        f"attribute(s) {missing}. Supported: MDM (trans_enc/trans_dec), DiP, "
                        "priorMDM doubleTake_MDM, smdm_plugin.TinyMDM; MotionDiffuse: "
                        "smdm_plugin.adapters.motiondiffuse.sparsify_motiondiffuse")
    arch = model.arch
    if arch == "trans_enc" and isinstance(getattr(model, "seqTransEncoder", None), nn.TransformerEncoder):
        attr = "seqTransEncoder"
    elif arch == "trans_dec" and isinstance(getattr(model, "seqTransDecoder", None), nn.TransformerDecoder):
        attr = "seqTransDecoder"
    else:
        raise TypeError(f"sparsify: arch={arch!r} of {type(model).__name__} is not supported (need "
                        "'trans_enc' with an nn.TransformerEncoder seqTransEncoder or 'trans_dec' with an "
                        "nn.TransformerDecoder seqTransDecoder; 'gru' has no attention to sparsify)")
    prefix = int(getattr(model, "context_len", 0) or 0) if getattr(model, "is_prefix_comp", False) else 0
    if prefix:
        name = "dip"
    elif "doubletake" in type(model).__name__.lower():
        name = "doubletake"
    else:
        name = f"mdm-{arch}" + ("-emb" if getattr(model, "emb_trans_dec", False) and arch == "trans_dec" else "")
    return Variant(arch=arch, transformer=attr, prefix_len=prefix, name=name)


def is_sparse(model: nn.Module) -> bool:
    """Whether ``model`` itself was sparsified (see :func:`sparsify`)."""
    return get_state(model) is not None


def _swap_lipschitz(model: nn.Module, config: SparseConfig, originals: Dict[Tuple[nn.Module, str], nn.Module]
                    ) -> None:
    latent = int(getattr(model, "latent_dim", model.output_process.poseFinal.in_features))
    hidden = config.lipschitz_hidden or latent
    for owner, names in ((model.input_process, ("poseEmbedding", "velEmbedding")),
                         (model.output_process, ("poseFinal", "velFinal"))):
        for name in names:
            old = getattr(owner, name, None)
            if not isinstance(old, nn.Linear):
                continue
            new = LipschitzMLP(old.in_features, old.out_features, hidden=hidden,
                               layers=config.lipschitz_layers, w0=config.sine_w0)
            new.to(device=old.weight.device, dtype=old.weight.dtype)
            originals[(owner, name)] = old
            setattr(owner, name, new)


def _call_args(args: tuple, kwargs: dict):
    x = args[0] if args else kwargs["x"]
    timesteps = args[1] if len(args) > 1 else kwargs.get("timesteps")
    y = args[2] if len(args) > 2 else kwargs.get("y")
    return x, timesteps, (y if y is not None else {})


def call_plan(state: SparseState, x: torch.Tensor, timesteps: Any, y: Dict[str, Any]) -> KeyframePlan:
    """The keyframe plan of one call ``model(x [B, J, F, N], timesteps [B], y)``."""
    B, N = x.shape[0], x.shape[-1]
    device = x.device
    lengths = lengths_from_y(y, B, N, device)
    forced = forced_from_y(y, B, N, device)
    valid = torch.arange(N, device=device)[None] < lengths[:, None]
    mask = y.get("keyframe_mask")
    if mask is not None:                                   # training (or a caller's own mask)
        mask = torch.as_tensor(mask, device=device)
        if tuple(mask.shape) != (B, N):
            raise ValueError(f"y['keyframe_mask'] must be bool [B, N]=[{B}, {N}], got {tuple(mask.shape)}")
        mask = mask.to(torch.bool) & valid
        if forced is not None:
            mask = mask | (forced & valid)
        capacity = y.get("keyframe_capacity")
        if capacity is None:                               # a mask from elsewhere: size it safely
            capacity = int(mask.sum(1).max()) if host_checkable(mask) and B else N
        check, cubic = True, None
    else:                                                  # sampling: the schedule on x_t
        t = timesteps if timesteps is not None else torch.zeros(B, dtype=torch.long, device=device)
        mask = state.schedule.sampling_mask(frames_layout(x), t, lengths, forced, checked=True)
        capacity = state.schedule.capacity(N, training=False, forced=protected_count(forced, lengths))
        check = False                                      # 2..capacity keyframes by construction
        cubic = state.schedule.cubic_samples(t, B, device)
    capacity = max(1, min(int(capacity), N))
    prefix = state.variant.prefix_len
    if prefix:
        mask = torch.cat([mask.new_ones(B, prefix), mask], dim=1)
        capacity += prefix
    return KeyframePlan.build(mask, capacity, check=check, cubic=cubic)


def _pre_hook(model: nn.Module, args: tuple, kwargs: dict):
    state: SparseState = getattr(model, STATE_ATTR)
    x, timesteps, y = _call_args(args, kwargs)
    state.plan = call_plan(state, x, timesteps, y)
    state.transformer.set_plan(state.plan)
    return None


def _post_hook(model: nn.Module, args: tuple, kwargs: dict, output: Any) -> Any:
    state: SparseState = getattr(model, STATE_ATTR)
    plan = state.plan
    state.transformer.set_plan(None)
    state.plan = None
    if plan is None or plan.cubic is None or not isinstance(output, torch.Tensor) or output.dim() != 4:
        return None
    return cubic_output(output, plan)


def cubic_output(output: torch.Tensor, plan: KeyframePlan) -> torch.Tensor:
    """``sample_interpolation="cubic"``: the model's output ``[B, J, F, N]`` with every frame of the
    samples in ``plan.cubic`` (the others unchanged) on the C¹ Catmull-Rom curve through the output at the plan's keyframes
    (which it keeps exactly; a DiP prefix is the plan's first frames). Static shapes, no sync."""
    B, J, F_, N = output.shape
    frames = frames_layout(output)                                          # [B, N, J*F]
    filled = interpolate_keyframes_cubic(frames, plan.mask[:, plan.frames - N:])
    filled = torch.where(plan.cubic.view(B, 1, 1), filled, frames)          # the others as they are
    return filled.reshape(B, N, J, F_).permute(0, 2, 3, 1)


# Input embedding on keyframe rows only (speed; outputs unchanged). Only keyframe tokens enter the
# keyframe transformer (every backend reads kept tokens only, and the output of the other frames
# is interpolated from the kept ones), so the embedding of the other frames is never used: the
# hooks below hand ``poseEmbedding`` the rows of the plan's slots ``[K*B, F]`` (static shape; on
# the CPU in eager mode, exactly the keyframe rows) and scatter its output back to ``[N, B, d]``
# with zeros elsewhere. They are plain functions that find the model's state through an attribute
# (not a closure), so ``copy.deepcopy`` (EMA) keeps each copy on its own state.
def _rows_pre_hook(module: nn.Module, args: tuple):
    state: Optional[SparseState] = getattr(module, "_smdm_rows_state", None)
    plan = None if state is None else state.plan
    x = args[0] if args else None
    if (plan is None or not isinstance(x, torch.Tensor) or x.dim() != 3 or len(args) != 1
            or x.shape[0] != plan.frames or x.shape[1] != plan.batch):
        if state is not None:
            state.embed_rows = None
        return None
    N, B, F_ = x.shape
    if host_checkable(plan.mask):                          # exact keyframe rows (data-dependent size)
        rows = plan.mask.t().reshape(-1).nonzero(as_tuple=True)[0]
    else:                                                  # every slot's frame: K*B rows, distinct
        rows = (plan.slot_frames() * B + torch.arange(B, device=x.device)).reshape(-1)
    state.embed_rows = (rows, N, B)
    return (gather_rows(x.reshape(N * B, F_), rows),)


def _rows_post_hook(module: nn.Module, args: tuple, output: torch.Tensor):
    state: Optional[SparseState] = getattr(module, "_smdm_rows_state", None)
    rows = None if state is None else state.embed_rows
    if rows is None:
        return None
    idx, N, B = rows
    state.embed_rows = None
    return scatter_rows(output, idx, N * B).view(N, B, output.shape[-1])


def sparsify(model: nn.Module, config: Optional[SparseConfig] = None, *, diffusion: Any = None,
             mean: Any = None, std: Any = None) -> nn.Module:
    """Convert ``model`` to sparse keyframe mode in place and return it.

    Args:
        model: an MDM-family model (see module docstring).
        config: the options; ``config.enabled=False`` returns ``model`` untouched.
        diffusion: if given, its ``training_losses`` is wrapped (:func:`attach_diffusion`) so that
            training masks come from x0 and ``lipschitz_lambda * L_lip`` joins the loss; its step
            count becomes ``config.diffusion_steps``.
        mean, std: ``[D]`` dataset statistics used to de-normalise motions for VW (HumanML3D/KIT).
    """
    config = config if config is not None else SparseConfig()
    if not config.enabled:
        return model
    if is_sparse(model):
        raise ValueError(f"sparsify: {type(model).__name__} is already sparse (unsparsify it first)")
    variant = detect_variant(model)
    if variant.prefix_len and config.prefix_frames not in (0, variant.prefix_len):
        raise ValueError(f"sparsify: config.prefix_frames={config.prefix_frames} but the DiP model has "
                         f"context_len={variant.prefix_len}")
    if diffusion is not None:
        config = config.replace(diffusion_steps=diffusion_steps(diffusion))
    if variant.prefix_len:
        config = config.replace(prefix_frames=variant.prefix_len)
    originals: Dict[Tuple[nn.Module, str], nn.Module] = {}
    if config.lipschitz:
        _swap_lipschitz(model, config, originals)
    inner = getattr(model, variant.transformer)
    n_fsq = 0
    if config.fsq:
        n_fsq = quantize_attention_keys(inner, config.fsq_levels)
    # always interpolate: the "w/o interpolation" ablation (config.interpolate=False) changes the
    # training loss (keyframes only, adapters/diffusion.py), sampling still returns every frame
    wrapper = KeyframeTransformer(inner, interpolate=True, backend=config.attention_backend)
    originals[(model, variant.transformer)] = inner
    setattr(model, variant.transformer, wrapper)
    ref = next(model.parameters())
    model.register_buffer(MARKER, torch.tensor(config.version, device=ref.device), persistent=True)
    model.smdm_config = config
    state = SparseState(config=config, variant=variant, transformer=wrapper,
                        schedule=MaskSchedule(config, mean, std), originals=originals, fsq_layers=n_fsq)
    setattr(model, STATE_ATTR, state)
    state.handles += [model.register_forward_pre_hook(_pre_hook, with_kwargs=True),
                      model.register_forward_hook(_post_hook, with_kwargs=True)]
    embed = getattr(model.input_process, "poseEmbedding", None)
    if isinstance(embed, nn.Module):
        embed._smdm_rows_state = state
        state.handles += [embed.register_forward_pre_hook(_rows_pre_hook),
                          embed.register_forward_hook(_rows_post_hook)]
    if diffusion is not None:
        attach_diffusion(diffusion, config, model=model)
    return model


def unsparsify(model: nn.Module) -> nn.Module:
    """Undo :func:`sparsify`: put back the original dense layers and remove the hooks.

    The dense input/output layers come back with the weights they had when the model was
    sparsified; weights learned in sparse mode by the Lipschitz MLPs are dropped (they have no
    dense equivalent). FSQ-quantised self-attention layers become ``nn.MultiheadAttention`` again
    with their current (trained) q/k/v/out weights; the key codebook projections are dropped.
    """
    if not is_sparse(model):
        return model
    state = get_state(model)
    release_diffusions(model)
    for h in state.handles:
        h.remove()
    embed = getattr(model.input_process, "poseEmbedding", None)
    if embed is not None and hasattr(embed, "_smdm_rows_state"):
        del embed._smdm_rows_state
    for (owner, name), module in state.originals.items():
        setattr(owner, name, module)
    if state.fsq_layers:
        unquantize_attention_keys(getattr(model, state.variant.transformer))
    del model._buffers[MARKER]
    delattr(model, STATE_ATTR)
    del model.smdm_config
    return model


def set_mean_std(model: nn.Module, mean: Any, std: Any) -> None:
    """Give a sparse model the dataset Mean/Std after the fact (e.g. once the data is loaded)."""
    get_state(model).schedule = MaskSchedule(model.smdm_config, mean, std)
