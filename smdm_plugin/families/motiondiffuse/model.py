"""Sparse keyframe mode for MotionDiffuse's ``MotionTransformer`` (text2motion/models/transformer.py)."""
from __future__ import annotations

import types
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Dict, Optional, Tuple

import numpy as np
import torch
import torch.nn as nn

from ...core.fill import fill_frames
from ...core.rows import gather_rows
from ...core.checks import as_lengths
from ...core.config import SparseConfig
from ...reference.embedding import timestep_embedding
from ...core.interpolation import catmull_rom_refill
from ...core import consts
from ...core.lipschitz import lipschitz_loss
from ...adapters.call import CallInputs, reuse_for
from ...adapters.family import ModelFamily, Variant
from ...adapters.request import KEYFRAMES_KEY, OLD_KEYS, request_of, with_request
from ...adapters.state import MISSING, FamilyState, SparseState, family_state_of, find_sparse_model, get_state


@dataclass
class MotionDiffuseState(FamilyState):
    """What the MotionDiffuse family keeps on a sparse model (``state.family_state``):
    ``timestep_embedding`` (the sinusoidal diffusion-step embedding of the model's module, fixed at
    ``sparsify``) and ``last_mask`` (bool ``[B, T]``, the keyframes of the latest call, read by
    :func:`trainer_loss` after the call)."""

    timestep_embedding: Callable[[torch.Tensor, int], torch.Tensor]
    last_mask: Optional[torch.Tensor] = None


def motiondiffuse_state(state: SparseState) -> MotionDiffuseState:
    """``state.family_state`` of a model the MotionDiffuse family converted."""
    return family_state_of(state, MotionDiffuseState)

_REQUIRED = ("joint_embed", "out", "temporal_decoder_blocks", "sequence_embedding", "time_embed",
             "encode_text", "latent_dim", "input_feats")


def _timestep_embedding_fn(model: nn.Module):
    """The upstream module's own ``timestep_embedding`` when importable, else ours (identical)."""
    mod = __import__(type(model).__module__, fromlist=["_"])
    return getattr(mod, "timestep_embedding", timestep_embedding)


def _lengths(length: Any, B: int, T: int, device: torch.device) -> torch.Tensor:
    """``length`` (MotionDiffuse's ``[B]`` list / tensor, or None = all ``T``) as long ``[B]``,
    validated (``2 <= L <= T``)."""
    if isinstance(length, torch.Tensor):            # read and checked once per tensor (call.reuse_for)
        return reuse_for(length, ("length", B, T, device), lambda: as_lengths(length, B, T, device, "MotionDiffuse length"))
    return as_lengths(length, B, T, device, "MotionDiffuse length")


# --------------------------------------------------------------------------- forward
def _sparse_forward(self, x, timesteps, length=None, text=None, xf_proj=None, xf_out=None, **request):
    """Sparse ``MotionTransformer.forward``: same arguments and output ``[B, T, D]``, plus the
    keyword ``smdm_keyframes=`` (a :class:`~smdm_plugin.adapters.request.KeyframeRequest`)."""
    state: SparseState = get_state(self)
    B, T = x.shape[0], x.shape[1]
    if text is not None and len(text) != B:  # upstream's per-GPU slice of a replicated text list
        index = x.device.index or 0
        text = text[index * B: index * B + B]
    if xf_proj is None or xf_out is None:
        xf_proj, xf_out = self.encode_text(text, x.device)
    emb = self.time_embed(motiondiffuse_state(state).timestep_embedding(timesteps, self.latent_dim)) + xf_proj

    return _sparse_body(self, state, x, emb, xf_out, timesteps, length, request)


def _sparse_body(self, state: SparseState, x, emb, xf_out, timesteps, length, request):
    B, T = x.shape[0], x.shape[1]
    h = self.joint_embed(x)
    h = h + self.sequence_embedding.unsqueeze(0)[:, :T, :]

    plan = state.family.read_call(state, (x, timesteps, length), request).plan(state)
    motiondiffuse_state(state).last_mask = plan.mask
    D = h.shape[-1]
    K = plan.capacity
    base = consts.arange(B, x.device)
    hk = gather_rows(h.reshape(B * T, D), torch.add(plan.index, base[:, None], alpha=T).reshape(-1)).view(B, K, D)
    src_mask = plan.valid.to(h.dtype).unsqueeze(-1)                      # empty slots masked
    for block in self.temporal_decoder_blocks:
        hk = block(hk, xf_out, emb, src_mask)
    rows = consts.arange(B * K, x.device).view(B, K).t()                 # [K, B] rows of hk: b * K + k
    h = fill_frames(hk.reshape(B * K, D), rows, plan, 0).transpose(0, 1)  # [B, T, D]
    out = self.out(h).view(B, T, -1)
    if plan.cubic is not None:  # sample_interpolation="cubic": C¹ through the keyframe outputs
        out = catmull_rom_refill(out, plan)
    return out.contiguous()


# --------------------------------------------------------------------------- the family
class MotionDiffuseFamily(ModelFamily):
    """MotionDiffuse's ``MotionTransformer``: ``forward(x [B, T, D], timesteps [B], length, text,
    xf_proj, xf_out)``; lengths in ``length``; forced / training keyframes as the keyword
    ``smdm_keyframes`` (a :class:`~smdm_plugin.adapters.request.KeyframeRequest`) of ``model_kwargs``."""

    name = "motiondiffuse"

    def matches(self, model: nn.Module) -> bool:
        return all(hasattr(model, a) for a in _REQUIRED)

    def mismatch(self, model: nn.Module) -> str:
        return f"missing attribute(s) {[a for a in _REQUIRED if not hasattr(model, a)]}"

    def variant(self, model: nn.Module) -> Variant:
        return Variant(arch="motiondiffuse", transformer="temporal_decoder_blocks", prefix_len=0,
                       name="motiondiffuse")

    def prepare_config(self, model: nn.Module, config: SparseConfig, variant: Variant) -> SparseConfig:
        if config.fsq:  # FSQ keys are defined for softmax attention; MotionDiffuse's is linear
            warnings.warn("sparsify: MotionDiffuse's self-attention is linear (no softmax keys to quantise): "
                          "fsq=True cannot apply and is turned off (the saved config says fsq=false)",
                          stacklevel=3)
            config = config.replace(fsq=False)
        if config.prefix_frames:
            raise ValueError(f"sparsify: MotionDiffuse has no dense prefix frames; config.prefix_frames must "
                             f"be 0, got {config.prefix_frames}")
        return config

    def io_layers(self, model: nn.Module):
        return [(model, "joint_embed"), (model, "out")]

    def install(self, model: nn.Module, state: SparseState) -> None:
        state.family_state = MotionDiffuseState(timestep_embedding=_timestep_embedding_fn(model))
        state.originals[(model, "forward")] = model.__dict__.get("forward", MISSING)
        model.forward = types.MethodType(_sparse_forward, model)

    def read_call(self, state: SparseState, args: tuple, kwargs: Dict[str, Any]) -> CallInputs:
        x, timesteps, length = args
        unknown = sorted(set(kwargs) - {KEYFRAMES_KEY, *OLD_KEYS})
        if unknown:
            raise TypeError(f"MotionTransformer.forward() got unexpected keyword argument(s) {unknown}")
        B, T = x.shape[:2]
        return CallInputs.of(x.detach(), timesteps, _lengths(length, B, T, x.device),
                             request_of(kwargs, "model_kwargs"), "model_kwargs")

    def training_inputs(self, state: SparseState, x_start: torch.Tensor, model_kwargs: Dict[str, Any]):
        request = {k: v for k, v in model_kwargs.items() if k in (KEYFRAMES_KEY, *OLD_KEYS)}
        return self.read_call(state, (x_start, None, model_kwargs.get("length")), request)

    def with_keyframes(self, state: SparseState, model_kwargs: Dict[str, Any], mask: torch.Tensor,
                       capacity: Optional[int]) -> Dict[str, Any]:
        return with_request(model_kwargs, "model_kwargs", mask=mask, capacity=capacity)

    def finish_losses(self, state: SparseState, model: nn.Module, terms: Dict[str, Any],
                      mask: torch.Tensor) -> Dict[str, Any]:
        terms["keyframe_mask"] = mask   # upstream's terms are pred/target; the loss is trainer_loss's
        return terms



# --------------------------------------------------------------------------- loss
def trainer_loss(trainer: Any, upstream_loss: torch.Tensor) -> torch.Tensor:
    """The loss of MotionDiffuse's ``DDPMTrainer.backward_G`` in sparse mode, from upstream's own.

    ``upstream_loss``: what ``backward_G`` computed (MSE between ``trainer.fake_noise`` and
    ``trainer.real_noise`` per frame, weighted by ``trainer.src_mask``: every valid frame, keyframe
    or interpolated, counts once). Returned: that loss (the same tensor, when interpolating) or, for
    ``config.interpolate=False``, the same MSE over valid keyframes only (the mask of the latest
    forward call); plus ``lipschitz_lambda * L_lip``. A dense encoder gets ``upstream_loss`` back.
    """
    sparse = find_sparse_model(trainer.encoder)
    if sparse is None:
        return upstream_loss
    state = get_state(sparse)
    config = state.config
    loss = upstream_loss
    if not config.interpolate:
        src = trainer.src_mask
        frame_mask = src.reshape(src.shape[0], -1).bool()
        last = motiondiffuse_state(state).last_mask
        if last is None or last.shape != frame_mask.shape:
            raise RuntimeError("trainer_loss: no keyframe mask of shape [B, T] from the latest forward "
                               "(call the sparse model through training_losses first)")
        frame_mask = frame_mask & last.to(frame_mask.device)
        err = ((trainer.fake_noise - trainer.real_noise) ** 2).mean(dim=-1)
        w = frame_mask.to(err.dtype)
        loss = (err * w).sum() / w.sum().clamp_min(1.0)
    if config.lipschitz and config.lipschitz_lambda > 0:
        loss = loss + config.lipschitz_lambda * lipschitz_loss(state.lipschitz_mlps)
    return loss


# --------------------------------------------------------------------------- options
def training_mean_std(mean: np.ndarray, std: np.ndarray, feat_bias: float = 25.0,
                      joints_num: int = 22) -> Tuple[np.ndarray, np.ndarray]:
    """The statistics MotionDiffuse's training set normalises with: ``Std.npy`` with the root
    (features 0-3) and foot-contact (last 4) entries divided by ``feat_bias``."""
    mean = np.asarray(mean, dtype=np.float32).copy()
    std = np.asarray(std, dtype=np.float32).copy()
    D = 4 + (joints_num - 1) * 9 + joints_num * 3 + 4
    if std.shape[-1] != D:
        raise ValueError(f"training_mean_std: expected [{D}] statistics for {joints_num} joints, "
                         f"got {std.shape}")
    std[:4] /= feat_bias
    std[-4:] /= feat_bias
    return mean, std
