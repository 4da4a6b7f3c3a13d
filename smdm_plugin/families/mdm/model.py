"""The MDM family: MDM trans_enc / trans_dec, DiP, the in-package ``TinyMDM`` (priorMDM's
doubleTake_MDM: :mod:`smdm_plugin.families.doubletake.model`, a specialisation of this one)."""
from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Tuple

import torch
import torch.nn as nn

from ...core.rows import gather_rows, scatter_rows
from ...core.checks import as_lengths, as_mask, compiling, host_checkable, require
from ...core.config import SparseConfig
from ...core.fsq import FSQMultiheadAttention, quantize_attention_keys
from ...core.interpolation import catmull_rom_refill
from ...core.keyframe_transformer import KeyframeTransformer
from ...core.losses import add_lipschitz_term
from ...core.plan import KeyframePlan
from ...adapters.call import CallInputs, reuse_for
from ...adapters.diffusion_wrapper import training_keyframes
from ...adapters.family import ModelFamily, Variant
from ...adapters.request import KEYFRAMES_KEY, request_of, with_request
from ...adapters.state import MISSING, STATE_ATTR, FamilyState, SparseState, family_state_of


@dataclass
class MDMState(FamilyState):
    """What the MDM family keeps on a sparse model (``state.family_state``): ``transformer``, the
    :class:`~smdm_plugin.core.keyframe_transformer.KeyframeTransformer` that replaced the dense
    one; per call ``embed_rows`` (the frame-major rows the input embedding ran on, written and
    cleared by the embedding hooks)."""

    transformer: KeyframeTransformer
    embed_rows: Optional[Tuple[torch.Tensor, int, int]] = None


def mdm_state(state: SparseState) -> MDMState:
    """``state.family_state`` of a model the MDM family (or a subclass) converted."""
    return family_state_of(state, MDMState)


def is_doubletake_model(model: nn.Module) -> bool:
    """Whether ``model``'s class is priorMDM's DoubleTake (``doubleTake_MDM``: by its name)."""
    return "doubletake" in type(model).__name__.lower()


# ----------------------------------------------------------------------------- MDM's calls
def frames_layout(x: torch.Tensor) -> torch.Tensor:
    """MDM's ``[B, J, F, N]`` motion as ``[B, N, J*F]``; ``[B, N, D]`` passes through."""
    if x.dim() == 4:
        B, J, F_, N = x.shape
        return x.permute(0, 3, 1, 2).reshape(B, N, J * F_)
    return x


def lengths_from_y(y: Dict[str, Any], B: int, N: int, device: torch.device) -> torch.Tensor:
    """Valid frames per sample ``[B]`` long from MDM's ``y``: ``y['mask'] [B, 1, 1, N]`` when it
    covers the frames (at least 2 valid frames each), else ``y['lengths']`` (integers in
    ``[2, N]``), else all ``N``. Bad values are a ``ValueError`` (checked on the host when the data
    is on the CPU, with ``torch._assert_async`` on accelerators: no sync).

    One exception, decided from shapes alone: when ``y['mask']`` does not cover the ``N`` frames
    (``[B, 1, 1, M]``, ``M != N``), the conditions describe another length than the window being
    sampled: MDM's ``sample.generate`` with dataset prompts passes a one-frame placeholder mask and
    ``lengths`` 120 whatever ``--motion_length`` is. Then ``y['lengths']`` (still >= 2) are cut to
    ``N``, as the dense model treats every frame of the window as valid, with a warning."""
    mask = y.get("mask")
    if isinstance(mask, torch.Tensor) and mask.shape[-1] == N and mask.numel() == B * N:
        def from_mask() -> torch.Tensor:
            m = mask.reshape(B, N).to(device=device)
            lengths = m.sum(1) if m.dtype == torch.bool else m.to(torch.long).sum(1)   # a bool sum is long
            require(lengths >= 2, f"y['mask'] must mark at least 2 valid frames of the N={N} in every sample")
            return lengths
        return reuse_for(mask, ("mask", B, N, device), from_mask)
    if isinstance(mask, torch.Tensor) and mask.dim() and mask.shape[-1] != N and y.get("lengths") is not None:
        if not compiling():
            warnings.warn(f"y['mask'] covers {mask.shape[-1]} frames but the motion has N={N}: y['lengths'] "
                          f"are cut to N (MDM's sample.generate does this with dataset prompts)", stacklevel=3)
        return as_lengths(y["lengths"], B, N, device, "y['lengths']", clip=True)
    if y.get("lengths") is not None:
        return as_lengths(y["lengths"], B, N, device, "y['lengths']")
    return torch.full((B,), N, dtype=torch.long, device=device)




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
    elif is_doubletake_model(model):
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
    own = mdm_state(state)
    x, timesteps, y = _call_args(args, kwargs)
    state.plan = call_plan(state, x, timesteps, y)
    own.transformer.set_plan(state.plan)
    return None


def _post_hook(model: nn.Module, args: tuple, kwargs: dict, output: Any) -> Any:
    state: SparseState = getattr(model, STATE_ATTR)
    own = mdm_state(state)
    plan = state.plan
    own.transformer.set_plan(None)
    state.plan = None
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
    plan, own = state.plan, mdm_state(state)
    x = args[0] if args else None
    if (plan is None or not isinstance(x, torch.Tensor) or x.dim() != 3 or len(args) != 1
            or x.shape[0] != plan.frames or x.shape[1] != plan.batch):
        own.embed_rows = None
        return None
    N, B, F_ = x.shape
    if not host_checkable(plan.mask):   # static path (accelerators): every row, no gather / scatter
        own.embed_rows = None           # (6 launches a training step, 3 a pass, for a few rows' FLOPs)
        return None
    rows = plan.mask.t().reshape(-1).nonzero(as_tuple=True)[0]   # exact keyframe rows (data-dependent size)
    own.embed_rows = (rows, N, B)
    return (gather_rows(x.reshape(N * B, F_), rows),)


def _rows_post_hook(state: SparseState, module: nn.Module, args: tuple, output: torch.Tensor):
    own = mdm_state(state)
    rows = own.embed_rows
    if rows is None:
        return None
    idx, N, B = rows
    own.embed_rows = None
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
        if config.fsq:                                    # FSQ keys in the self-attention
            for m in inner.modules():
                if isinstance(getattr(m, "self_attn", None), nn.MultiheadAttention):
                    state.originals[(m, "self_attn")] = m.self_attn
            before = set(inner._modules)
            quantize_attention_keys(inner, config.fsq_levels)     # (before the wrapper: it takes the bank too)
            for name in inner._modules:
                if name not in before:                    # the key maps' bank
                    state.originals[(inner, name)] = MISSING
            if isinstance(inner, nn.TransformerEncoder):   # FSQ layers: no nested-tensor fast path
                state.originals[(inner, "use_nested_tensor")] = inner.use_nested_tensor
                inner.use_nested_tensor = False
        # always interpolate: the "w/o interpolation" ablation (config.interpolate=False) changes the
        # training loss (keyframes only, with_keyframes below), sampling still returns every frame
        wrapper = KeyframeTransformer(inner, interpolate=True, backend=config.attention_backend)
        state.originals[(model, attr)] = inner
        setattr(model, attr, wrapper)
        state.family_state = MDMState(transformer=wrapper)
        state.handles += [model.register_forward_pre_hook(_pre_hook, with_kwargs=True),
                          model.register_forward_hook(_post_hook, with_kwargs=True)]
        embed = getattr(model.input_process, "poseEmbedding", None)
        if isinstance(embed, nn.Module):
            state.handles += [embed.register_forward_pre_hook(functools.partial(_rows_pre_hook, state)),
                              embed.register_forward_hook(functools.partial(_rows_post_hook, state))]

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
        return add_lipschitz_term(terms, state.lipschitz_mlps, state.config, mask.shape[0])



class keyframe_collate:
    """Wrap an MDM-style ``collate_fn`` (returns ``(motion [B, J, F, N], {'y': {...}})``) so that the
    training keyframes are chosen while loading, on the CPU, in the loader's worker processes:
    ``y[KEYFRAMES_KEY]`` gets their ``mask`` and ``capacity`` (a
    :class:`~smdm_plugin.adapters.request.KeyframeRequest`), and the diffusion wrapper uses them
    instead of selecting on the GPU. The mask depends only on x0, so the result is the same
    (mask noise is drawn in the worker). ``schedule``: the sparse model's
    ``MaskSchedule`` (``model._smdm_state.schedule``); it must be picklable for worker processes.

    Mask noise comes from the schedule's noise table (:mod:`~smdm_plugin.core.noise`) at a step
    counted per batch and, in a worker process, offset by the worker's seed (new every epoch);
    torch's global stream is not drawn from (with ``num_workers=0`` it is the training process's)."""

    def __init__(self, collate_fn: Callable[[Any], Tuple[torch.Tensor, Dict[str, Any]]], schedule: Any) -> None:
        self.collate_fn, self.schedule = collate_fn, schedule
        self.batches = 0

    def __call__(self, batch: Any) -> Tuple[torch.Tensor, Dict[str, Any]]:
        motion, cond = self.collate_fn(batch)
        y = cond["y"]
        frames = frames_layout(motion)
        B, N = frames.shape[:2]
        lengths = lengths_from_y(y, B, N, motion.device)
        forced = as_mask(request_of(y).forced, B, N, motion.device, f"y[{KEYFRAMES_KEY!r}].forced")
        worker = torch.utils.data.get_worker_info()
        offset = (worker.seed % (1 << 32)) * 65537 if worker is not None else 0
        step = torch.tensor(self.batches + offset, dtype=torch.long, device=motion.device)
        self.batches += 1
        mask, capacity = training_keyframes(self.schedule, frames, lengths, forced, self.schedule.noise(step))
        cond["y"] = with_request(y, mask=mask, capacity=capacity)
        return motion, cond
