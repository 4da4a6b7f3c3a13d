"""Sparse keyframe mode for MotionDiffuse's ``MotionTransformer`` (text2motion/models/transformer.py).

MotionDiffuse's denoiser embeds every frame (``joint_embed``), adds a learned per-frame
``sequence_embedding``, runs ``temporal_decoder_blocks`` (linear self-attention, cross-attention
to the text, FFN; each conditioned on the timestep+text embedding) and maps back with ``out``.
Its self-attention is *linear* (softmax kernels, ``O(T d^2)``), so the saving of sparse mode is in
the number of tokens: here only keyframe tokens go through the decoder blocks.

:func:`sparsify_motiondiffuse` changes the instance in place:

* ``joint_embed`` / ``out`` become Lipschitz sine MLPs (``config.lipschitz``);
* ``forward`` is replaced by a bound method that gathers the keyframe tokens (after the
  positional ``sequence_embedding`` is added, so every token keeps its frame position), builds
  ``src_mask`` over the gathered tokens (padding tokens of rows with fewer keyframes are masked
  exactly like upstream masks padded frames), runs the blocks, scatters the tokens back and
  linearly interpolates the hidden features to all frames before ``out``;
* the keyframe mask is the ``keyframe_mask`` keyword when given (training: chosen from x0 by
  the wrapped ``training_losses``), else the sampling schedule on ``(x_t, timesteps)``;
  ``keyframe_forced`` is OR-ed in;
* a persistent buffer ``smdm_sparse_version`` marks the state dict as sparse.

:func:`unsparsify_motiondiffuse` puts the original layers and ``forward`` back.

The loss. MotionDiffuse trains on the loss of ``DDPMTrainer.backward_G``: the per-frame MSE
weighted by ``src_mask`` (frames before each motion's length), i.e. padded frames already excluded.
``GaussianDiffusion.training_losses`` only returns ``pred`` / ``target`` (and an unused ``mse``), so
the dense loss needs no fix. In sparse mode every valid frame still counts: keyframes (model
outputs) and the frames between them (interpolated from the keyframes' hidden features), exactly
the frames upstream's ``src_mask`` selects; padded frames are never keyframes, never enter the
decoder blocks, and stay out of the loss as upstream. What sparse mode adds is
:func:`trainer_loss`: ``+ lipschitz_lambda * L_lip`` and, for the keyframes-only ablation
(``config.interpolate=False``), the loss on keyframes only. :func:`attach_motiondiffuse_diffusion`
chooses each training sample's keyframes from ``x_start`` and passes them to the model.
"""
from __future__ import annotations

import functools
import math
import types
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Optional, Tuple

import numpy as np
import torch
import torch.nn as nn

from ..core.config import MARKER, SparseConfig
from ..core.interpolation import interpolate_keyframes, interpolate_keyframes_cubic
from ..core.lipschitz import LipschitzMLP, lipschitz_loss
from ..core.schedule import MaskSchedule

_REQUIRED = ("joint_embed", "out", "temporal_decoder_blocks", "sequence_embedding", "time_embed",
             "encode_text", "latent_dim", "input_feats")


MD_STATE_ATTR = "_smdm_md_state"


@dataclass
class MotionDiffuseState:
    """What :func:`sparsify_motiondiffuse` keeps on the model (``model._smdm_md_state``):
    the replaced layers and ``forward`` (for undoing), the mask schedule, the timestep
    embedding function, and ``last_mask`` (bool ``[B, T]``, the keyframes of the latest call)."""

    schedule: MaskSchedule
    timestep_embedding: Callable[..., torch.Tensor]
    originals: Dict[str, nn.Module] = field(default_factory=dict)
    had_forward: bool = False
    old_forward: Any = None
    last_mask: Optional[torch.Tensor] = None


def _md_state(model: nn.Module) -> Optional[MotionDiffuseState]:
    return getattr(model, MD_STATE_ATTR, None)


# --------------------------------------------------------------------------- helpers
def _check_model(model: nn.Module) -> None:
    missing = [a for a in _REQUIRED if not hasattr(model, a)]
    if missing:
        raise TypeError(f"sparsify_motiondiffuse: {type(model).__name__} is not MotionDiffuse's "
                        f"MotionTransformer; missing attribute(s) {missing}")


def is_sparse_motiondiffuse(model: nn.Module) -> bool:
    return _md_state(model) is not None


def timestep_embedding(timesteps: torch.Tensor, dim: int, max_period: int = 10000) -> torch.Tensor:
    """Sinusoidal embedding ``[B, dim]`` (cos half, then sin half), as the denoiser expects."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32,
                                                           device=timesteps.device) / half)
    args = timesteps.reshape(-1, 1).float() * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=-1)
    return emb


def _timestep_embedding_fn(model: nn.Module):
    """The upstream module's own ``timestep_embedding`` when importable, else ours (identical)."""
    mod = __import__(type(model).__module__, fromlist=["_"])
    return getattr(mod, "timestep_embedding", timestep_embedding)


def valid_frames(lengths: Optional[torch.Tensor], B: int, T: int, device) -> torch.Tensor:
    """bool ``[B, T]``: frame < length."""
    if lengths is None:
        return torch.ones(B, T, dtype=torch.bool, device=device)
    L = torch.as_tensor(lengths, device=device).long().reshape(-1)
    if L.shape[0] != B:
        raise ValueError(f"MotionDiffuse sparse forward: length must be [B]=[{B}], got {tuple(L.shape)}")
    return torch.arange(T, device=device)[None] < L[:, None]


def gather_keyframes(h: torch.Tensor, mask: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Pack the keyframe tokens of ``h [B, T, D]`` to ``[B, K, D]`` (K = most keyframes in a row),
    in frame order; returns the packed tokens and their validity ``[B, K]`` bool."""
    counts = mask.sum(1)
    K = int(counts.max())
    tok_valid = torch.arange(K, device=h.device)[None] < counts[:, None]
    packed = h.new_zeros(h.shape[0], K, h.shape[-1])
    packed[tok_valid] = h[mask]
    return packed, tok_valid


def scatter_keyframes(packed: torch.Tensor, tok_valid: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`gather_keyframes`: ``[B, T, D]`` with zeros at non-keyframes."""
    out = packed.new_zeros(mask.shape[0], mask.shape[1], packed.shape[-1])
    out[mask] = packed[tok_valid]
    return out


# --------------------------------------------------------------------------- forward
def _sparse_forward(self, x, timesteps, length=None, text=None, xf_proj=None, xf_out=None,
                    keyframe_mask=None, keyframe_forced=None):
    """Sparse ``MotionTransformer.forward``: same arguments and output ``[B, T, D]``, plus
    ``keyframe_mask`` / ``keyframe_forced`` (bool ``[B, T]``)."""
    state: MotionDiffuseState = getattr(self, MD_STATE_ATTR)
    B, T = x.shape[0], x.shape[1]
    if text is not None and len(text) != B:  # upstream's per-GPU slice of a replicated text list
        index = x.device.index or 0
        text = text[index * B: index * B + B]
    if xf_proj is None or xf_out is None:
        xf_proj, xf_out = self.encode_text(text, x.device)
    emb = self.time_embed(state.timestep_embedding(timesteps, self.latent_dim)) + xf_proj

    h = self.joint_embed(x)
    h = h + self.sequence_embedding.unsqueeze(0)[:, :T, :]

    valid = valid_frames(length, B, T, x.device)
    cubic = None
    if keyframe_mask is None:
        lengths = valid.long().sum(1).clamp(2, T) if T >= 2 else valid.long().sum(1)
        t = timesteps if timesteps is not None else torch.zeros(B, device=x.device)
        mask = state.schedule.sampling_mask(x.detach(), t, lengths, keyframe_forced)
        cubic = state.schedule.cubic_samples(t, B, x.device)
    else:
        mask = torch.as_tensor(keyframe_mask, device=x.device).bool()
        if mask.shape != (B, T):
            raise ValueError(f"MotionDiffuse sparse forward: keyframe_mask must be bool [B, T]="
                             f"[{B}, {T}], got {tuple(mask.shape)}")
        if keyframe_forced is not None:
            mask = mask | torch.as_tensor(keyframe_forced, device=x.device).bool()
    mask = mask & valid
    empty = ~mask.any(1)
    if bool(empty.any()):  # a row without valid frames: keep its first frame
        mask = mask.clone()
        mask[empty, 0] = True
    state.last_mask = mask

    hk, tok_valid = gather_keyframes(h, mask)
    src_mask = tok_valid.to(h.dtype).unsqueeze(-1)
    for block in self.temporal_decoder_blocks:
        hk = block(hk, xf_out, emb, src_mask)
    h = interpolate_keyframes(scatter_keyframes(hk, tok_valid, mask), mask)
    out = self.out(h).view(B, T, -1)
    if cubic is not None:       # sample_interpolation="cubic": C¹ through the keyframe outputs
        out = torch.where(cubic.view(B, 1, 1), interpolate_keyframes_cubic(out, mask), out)
    return out.contiguous()


# --------------------------------------------------------------------------- (un)sparsify
def sparsify_motiondiffuse(model: nn.Module, config: Optional[SparseConfig] = None,
                           mean: Any = None, std: Any = None, *, diffusion: Any = None) -> nn.Module:
    """Turn MotionDiffuse's ``MotionTransformer`` into its sparse keyframe version, in place.

    Args:
        model: the ``MotionTransformer`` (not a DataParallel wrapper: pass ``.module``).
        config: the options; ``enabled=False`` returns ``model`` untouched. ``fsq`` is set to
            False (FSQ keys quantise softmax attention; MotionDiffuse's attention is linear), so
            the saved config says what ran.
        mean, std: ``[D]`` statistics the training data was normalised with (MotionDiffuse
            divides the root and foot-contact std by ``feat_bias``; see :func:`training_mean_std`).
        diffusion: MotionDiffuse's ``GaussianDiffusion``; its ``training_losses`` is wrapped
            (:func:`attach_motiondiffuse_diffusion`) and its step count becomes
            ``config.diffusion_steps``.
    """
    config = config if config is not None else SparseConfig()
    if not config.enabled:
        return model
    _check_model(model)
    if is_sparse_motiondiffuse(model):
        raise ValueError("sparsify_motiondiffuse: the model is already sparse (unsparsify it first)")
    if diffusion is not None and getattr(diffusion, "num_timesteps", None):
        config = config.replace(diffusion_steps=int(diffusion.num_timesteps))
    if config.fsq:   # FSQ keys are defined for softmax attention; MotionDiffuse's is linear
        config = config.replace(fsq=False)
    originals: Dict[str, nn.Module] = {}
    ref = model.sequence_embedding
    if config.lipschitz:
        hidden = config.lipschitz_hidden or model.latent_dim
        for name, fin, fout in (("joint_embed", model.input_feats, model.latent_dim),
                                ("out", model.latent_dim, model.input_feats)):
            originals[name] = getattr(model, name)
            mlp = LipschitzMLP(fin, fout, hidden=hidden, layers=config.lipschitz_layers,
                               w0=config.sine_w0).to(device=ref.device, dtype=ref.dtype)
            setattr(model, name, mlp)
    model.register_buffer(MARKER, torch.tensor(config.version, device=ref.device), persistent=True)
    model.smdm_config = config
    setattr(model, MD_STATE_ATTR, MotionDiffuseState(
        schedule=MaskSchedule(config, mean, std), timestep_embedding=_timestep_embedding_fn(model),
        originals=originals, had_forward="forward" in model.__dict__,
        old_forward=model.__dict__.get("forward")))
    model.forward = types.MethodType(_sparse_forward, model)
    if diffusion is not None:
        attach_motiondiffuse_diffusion(diffusion, config, model)
    return model


def unsparsify_motiondiffuse(model: nn.Module) -> nn.Module:
    """Undo :func:`sparsify_motiondiffuse` (dense layers come back with their old weights)."""
    if not is_sparse_motiondiffuse(model):
        return model
    state = _md_state(model)
    for name, module in state.originals.items():
        setattr(model, name, module)
    if state.had_forward:
        model.forward = state.old_forward
    else:
        del model.forward
    del model._buffers[MARKER]
    delattr(model, MD_STATE_ATTR)
    del model.smdm_config
    return model


def set_mean_std(model: nn.Module, mean: Any, std: Any) -> None:
    _md_state(model).schedule = MaskSchedule(model.smdm_config, mean, std)


# --------------------------------------------------------------------------- loss
def _find_md_sparse(model: nn.Module) -> Optional[nn.Module]:
    for m in model.modules():
        if _md_state(m) is not None:
            return m
    return None


def attach_motiondiffuse_diffusion(diffusion: Any, config: SparseConfig, model: Optional[nn.Module] = None
                                   ) -> Any:
    """Wrap MotionDiffuse's ``GaussianDiffusion.training_losses`` in place (idempotent): with a
    sparse model (``model``, else found inside the model it is called with) each sample's keyframes
    are chosen from ``x_start`` (+ mask noise) and passed to it as ``keyframe_mask``; the returned
    terms are upstream's plus ``terms['keyframe_mask']`` (bool ``[B, T]``). A dense model is run as
    upstream runs it. The training loss itself is :func:`trainer_loss`."""
    if getattr(diffusion, "_smdm_md_attached", False):
        return diffusion
    original = diffusion.training_losses
    bound_model = model

    @functools.wraps(original)
    def training_losses(model, x_start, t, model_kwargs=None, noise=None):
        # (keyword names as upstream: DDPMTrainer calls training_losses(model=..., x_start=...))
        sparse = bound_model if bound_model is not None else _find_md_sparse(model)
        if sparse is None or not config.enabled:
            return original(model, x_start, t, model_kwargs=model_kwargs, noise=noise)
        model_kwargs = dict(model_kwargs or {})
        B, T = x_start.shape[:2]
        lengths = valid_frames(model_kwargs.get("length"), B, T, x_start.device).long().sum(1).clamp(2, T)
        mask = _md_state(sparse).schedule.training_mask(
            x_start.detach(), lengths, model_kwargs.get("keyframe_forced"))
        model_kwargs["keyframe_mask"] = mask
        terms = original(model, x_start, t, model_kwargs=model_kwargs, noise=noise)
        terms["keyframe_mask"] = mask
        return terms

    diffusion.training_losses = training_losses
    diffusion._smdm_md_attached = True
    diffusion._smdm_md_original = original
    return diffusion


def detach_motiondiffuse_diffusion(diffusion: Any) -> Any:
    if getattr(diffusion, "_smdm_md_attached", False):
        del diffusion.training_losses
        del diffusion._smdm_md_attached
        del diffusion._smdm_md_original
    return diffusion


def trainer_loss(trainer: Any, upstream_loss: torch.Tensor) -> torch.Tensor:
    """The loss of MotionDiffuse's ``DDPMTrainer.backward_G`` in sparse mode, from upstream's own.

    ``upstream_loss``: what ``backward_G`` computed (MSE between ``trainer.fake_noise`` and
    ``trainer.real_noise`` per frame, weighted by ``trainer.src_mask``: every valid frame, keyframe
    or interpolated, counts once). Returned: that loss (the same tensor, when interpolating) or, for
    ``config.interpolate=False``, the same MSE over valid keyframes only (the mask of the latest
    forward call); plus ``lipschitz_lambda * L_lip``. A dense encoder gets ``upstream_loss`` back.
    """
    sparse = _find_md_sparse(trainer.encoder)
    config: Optional[SparseConfig] = getattr(sparse, "smdm_config", None)
    if sparse is None or config is None:
        return upstream_loss
    loss = upstream_loss
    if not config.interpolate:
        src = trainer.src_mask
        frame_mask = src.reshape(src.shape[0], -1).bool()
        last = _md_state(sparse).last_mask
        if last is None or last.shape != frame_mask.shape:
            raise RuntimeError("trainer_loss: no keyframe mask of shape [B, T] from the latest forward "
                               "(call the sparse model through training_losses first)")
        frame_mask = frame_mask & last.to(frame_mask.device)
        err = ((trainer.fake_noise - trainer.real_noise) ** 2).mean(dim=-1)
        w = frame_mask.to(err.dtype)
        loss = (err * w).sum() / w.sum().clamp_min(1.0)
    if config.lipschitz and config.lipschitz_lambda > 0:
        loss = loss + config.lipschitz_lambda * lipschitz_loss(sparse)
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
