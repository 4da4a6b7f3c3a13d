"""The MDM family: MDM trans_enc / trans_dec, DiP, the in-package ``TinyMDM`` (priorMDM's
doubleTake_MDM: :mod:`smdm_plugin.adapters.doubletake`, a specialisation of this one).

What ``sparsify`` (:mod:`smdm_plugin.adapters.surgery`) changes on such a model:

* ``input_process.poseEmbedding`` / ``output_process.poseFinal`` (and ``velEmbedding`` /
  ``velFinal`` when present) become Lipschitz sine MLPs (``config.lipschitz``);
* ``seqTransEncoder`` / ``seqTransDecoder`` is wrapped by :class:`KeyframeTransformer` (and its
  self-attention keys FSQ-quantised with ``config.fsq``);
* a forward pre-hook decides the keyframes of every call and builds its
  :class:`~smdm_plugin.core.plan.KeyframePlan` once from the call's
  :class:`~smdm_plugin.adapters.request.KeyframeRequest` (``y[KEYFRAMES_KEY]``): its ``mask`` when
  given (training: the diffusion wrapper selects it from x0, with its ``capacity``), else the
  sampling schedule on ``(x_t, timesteps)``; its ``forced`` frames are always keyframes (inside
  the budget); DiP's ``context_len`` prefix frames are always kept. The input embedding, the
  keyframe transformer and the interpolation all read that one plan.

A call has static shapes and no host synchronisation (unless forced keyframes live on an
accelerator: their count is read once to size the plan), so ``torch.compile(model,
fullgraph=True)`` and CUDA graphs work on the sparse model as on the dense one.
"""
from __future__ import annotations

import functools
from typing import Any, Dict, List, Optional

import torch
import torch.nn as nn

from ..core.attention_backends import gather_rows, scatter_rows
from ..core.checks import compiling, host_checkable
from ..core.config import SparseConfig
from ..core.fsq import FSQMultiheadAttention, quantize_attention_keys
from ..core.interpolation import catmull_rom_refill
from ..core.keyframe_transformer import KeyframeTransformer
from ..core.lipschitz import lipschitz_pass
from ..core.losses import add_lipschitz_term
from ..core.plan import KeyframePlan
from .family import CallInputs, ModelFamily, register_family
from .request import request_of, with_request
from .state import MISSING, STATE_ATTR, SparseState, Variant, frames_layout, lengths_from_y



def _missing_attrs(model: nn.Module) -> List[str]:
    """The MDM attributes ``model`` lacks (empty: it has MDM's structure)."""
    missing = [a for a in ("input_process", "output_process", "arch") if not hasattr(model, a)]
    if not missing:
        if not hasattr(model.input_process, "poseEmbedding"):
            missing.append("input_process.poseEmbedding")
        if not hasattr(model.output_process, "poseFinal"):
            missing.append("output_process.poseFinal")
    return missing


def detect_variant(model: nn.Module) -> Variant:
    """Recognise an MDM-family model by its structure; a clear error lists what is missing."""
    missing = _missing_attrs(model)
    if missing:
        raise TypeError(f"sparsify: {type(model).__name__} is not an MDM-family model; missing "
                        f"attribute(s) {missing}. Supported: MDM (trans_enc/trans_dec), DiP, "
                        "priorMDM doubleTake_MDM, smdm_plugin.TinyMDM")
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


def _call_args(args: tuple, kwargs: dict):
    x = args[0] if args else kwargs["x"]
    timesteps = args[1] if len(args) > 1 else kwargs.get("timesteps")
    y = args[2] if len(args) > 2 else kwargs.get("y")
    return x, timesteps, (y if y is not None else {})


def call_plan(state: SparseState, x: torch.Tensor, timesteps: Any, y: Dict[str, Any]) -> KeyframePlan:
    """The keyframe plan of one call ``model(x [B, J, F, N], timesteps [B], y)``."""
    return state.family.read_call(state, (x, timesteps, y), {}).plan(state)


def _pre_hook(model: nn.Module, args: tuple, kwargs: dict):
    state: SparseState = getattr(model, STATE_ATTR)
    x, timesteps, y = _call_args(args, kwargs)
    state.plan = call_plan(state, x, timesteps, y)
    state.transformer.set_plan(state.plan)
    if not compiling():                                    # training: all Lipschitz weights at once
        if state.lipschitz_pass is not None:               # (left by a call that raised)
            state.lipschitz_pass.__exit__(None, None, None)
        state.lipschitz_pass = lipschitz_pass(model).__enter__()
    return None


def _post_hook(model: nn.Module, args: tuple, kwargs: dict, output: Any) -> Any:
    state: SparseState = getattr(model, STATE_ATTR)
    plan = state.plan
    state.transformer.set_plan(None)
    state.plan = None
    if state.lipschitz_pass is not None:
        state.lipschitz_pass.__exit__(None, None, None)
        state.lipschitz_pass = None
    if plan is None or plan.cubic is None or not isinstance(output, torch.Tensor) or output.dim() != 4:
        return None
    return cubic_output(output, plan)


def cubic_output(output: torch.Tensor, plan: KeyframePlan) -> torch.Tensor:
    """``sample_interpolation="cubic"``: the model's output ``[B, J, F, N]`` with every frame of the
    samples in ``plan.cubic`` (the others unchanged) on the C¹ Catmull-Rom curve through the output
    at the plan's keyframes, which it keeps exactly (a DiP prefix is the plan's first frames; the
    output has none). Classifier-free guidance mixes two such curves on one mask: again one. Static
    shapes, no host sync."""
    B, J, F_, N = output.shape
    frames = frames_layout(output)                                          # [B, N, J*F]
    if plan.frames != N:                                                    # DiP: the output has no prefix
        plan = KeyframePlan.build(plan.mask[:, plan.frames - N:], None, check=False, cubic=plan.cubic)
    filled = catmull_rom_refill(frames, plan)                               # the others as they are
    return filled.reshape(B, N, J, F_).permute(0, 2, 3, 1)


# Input embedding on keyframe rows only (CPU speed; outputs unchanged). Only keyframe tokens enter
# the keyframe transformer (every backend reads kept tokens only, and the output of the other frames
# is interpolated from the kept ones), so the embedding of the other frames is never used: on the
# CPU in eager mode the hooks below hand ``poseEmbedding`` exactly the keyframe rows and scatter its
# output back to ``[N, B, d]`` with zeros elsewhere. On the static path (accelerators, tracing) they
# do nothing: the embedding of every row costs a few FLOPs, the gather and scatter three launches
# forward and three backward. They are registered as ``functools.partial(hook, state)``: the embedding
# carries no attribute of ours, and ``copy.deepcopy`` (EMA) copies the partial with the model, so
# each copy's hooks hold that copy's own state.
def _rows_pre_hook(state: SparseState, module: nn.Module, args: tuple):
    plan = state.plan
    x = args[0] if args else None
    if (plan is None or not isinstance(x, torch.Tensor) or x.dim() != 3 or len(args) != 1
            or x.shape[0] != plan.frames or x.shape[1] != plan.batch):
        state.embed_rows = None
        return None
    N, B, F_ = x.shape
    if not host_checkable(plan.mask):   # static path (accelerators): every row, no gather / scatter
        state.embed_rows = None         # (6 launches a training step, 3 a pass, for a few rows' FLOPs)
        return None
    rows = plan.mask.t().reshape(-1).nonzero(as_tuple=True)[0]   # exact keyframe rows (data-dependent size)
    state.embed_rows = (rows, N, B)
    return (gather_rows(x.reshape(N * B, F_), rows),)


def _rows_post_hook(state: SparseState, module: nn.Module, args: tuple, output: torch.Tensor):
    rows = state.embed_rows
    if rows is None:
        return None
    idx, N, B = rows
    state.embed_rows = None
    return scatter_rows(output, idx, N * B).view(N, B, output.shape[-1])


class MDMFamily(ModelFamily):
    """MDM's ``forward(x [B, J, F, N], timesteps [B], y)``; lengths in ``y['mask']`` /
    ``y['lengths']``, forced frames and training keyframes in ``y[KEYFRAMES_KEY]`` (a
    :class:`~smdm_plugin.adapters.request.KeyframeRequest`); DiP's prefix frames kept dense."""

    name = "mdm"

    def matches(self, model: nn.Module) -> bool:
        return not _missing_attrs(model)

    def mismatch(self, model: nn.Module) -> str:
        return f"missing attribute(s) {_missing_attrs(model)}"

    def variant(self, model: nn.Module) -> Variant:
        return detect_variant(model)

    def prepare_config(self, model: nn.Module, config: SparseConfig, variant: Variant) -> SparseConfig:
        if variant.prefix_len and config.prefix_frames not in (0, variant.prefix_len):
            raise ValueError(f"sparsify: config.prefix_frames={config.prefix_frames} but the DiP model has "
                             f"context_len={variant.prefix_len}")
        return config.replace(prefix_frames=variant.prefix_len) if variant.prefix_len else config

    def io_layers(self, model: nn.Module):
        return [(model.input_process, "poseEmbedding"), (model.input_process, "velEmbedding"),
                (model.output_process, "poseFinal"), (model.output_process, "velFinal")]

    def latent_dim(self, model: nn.Module) -> int:
        return int(getattr(model, "latent_dim", model.output_process.poseFinal.in_features))

    def install(self, model: nn.Module, state: SparseState) -> None:
        config, attr = state.config, state.variant.transformer
        inner = getattr(model, attr)
        # always interpolate: the "w/o interpolation" ablation (config.interpolate=False) changes the
        # training loss (keyframes only, with_keyframes below), sampling still returns every frame
        wrapper = KeyframeTransformer(inner, interpolate=True, backend=config.attention_backend)
        state.originals[(model, attr)] = inner
        setattr(model, attr, wrapper)
        state.transformer = wrapper
        state.handles += [model.register_forward_pre_hook(_pre_hook, with_kwargs=True),
                          model.register_forward_hook(_post_hook, with_kwargs=True)]
        embed = getattr(model.input_process, "poseEmbedding", None)
        if isinstance(embed, nn.Module):
            state.handles += [embed.register_forward_pre_hook(functools.partial(_rows_pre_hook, state)),
                              embed.register_forward_hook(functools.partial(_rows_post_hook, state))]
        if config.fsq:                                    # FSQ keys in the self-attention
            for m in inner.modules():
                if isinstance(getattr(m, "self_attn", None), nn.MultiheadAttention):
                    state.originals[(m, "self_attn")] = m.self_attn
            state.fsq_layers = quantize_attention_keys(inner, config.fsq_levels)
            if isinstance(inner, nn.TransformerEncoder):   # FSQ layers: no nested-tensor fast path
                state.originals[(inner, "use_nested_tensor")] = inner.use_nested_tensor
                inner.use_nested_tensor = False

    def uninstall(self, model: nn.Module, state: SparseState) -> None:
        """``unsparsify`` keeps the trained attention: each FSQ self-attention goes back as an
        ``nn.MultiheadAttention`` with its current q/k/v/out weights (a rolled-back ``sparsify``
        restores the original objects instead)."""
        for (owner, name), old in list(state.originals.items()):
            attn = getattr(owner, name, None)
            if name == "self_attn" and isinstance(attn, FSQMultiheadAttention):
                state.originals[(owner, name)] = attn.to_mha()

    def read_call(self, state: SparseState, args: tuple, kwargs: Dict[str, Any]) -> CallInputs:
        x, timesteps, y = _call_args(args, kwargs)
        B, N = x.shape[0], x.shape[-1]
        return CallInputs.of(frames_layout(x), timesteps, lengths_from_y(y, B, N, x.device), request_of(y), "y")

    def training_inputs(self, state: SparseState, x_start: torch.Tensor, model_kwargs: Dict[str, Any]):
        return self.read_call(state, (x_start, None, (model_kwargs or {}).get("y")), {})

    def with_keyframes(self, state: SparseState, model_kwargs: Dict[str, Any], mask: torch.Tensor,
                       capacity: Optional[int]) -> Dict[str, Any]:
        model_kwargs = dict(model_kwargs or {})
        y = with_request(model_kwargs.get("y"), mask=mask, capacity=capacity)
        if not state.config.interpolate and isinstance(y.get("mask"), torch.Tensor):
            y["mask"] = y["mask"] & mask.view(y["mask"].shape).to(y["mask"].dtype)   # keyframes-only loss
        model_kwargs["y"] = y
        return model_kwargs

    def finish_losses(self, state: SparseState, model: nn.Module, terms: Dict[str, Any],
                      mask: torch.Tensor) -> Dict[str, Any]:
        return add_lipschitz_term(terms, model, state.config, mask.shape[0])


register_family(MDMFamily())
