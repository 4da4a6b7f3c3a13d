"""Loss helpers: dense-frame loss with valid-length masking, the keyframe-only ablation, λ·L_lip."""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn as nn

from .lipschitz import MLPs, lipschitz_loss


def valid_frames(lengths: torch.Tensor, N: int) -> torch.Tensor:
    """bool ``[B, N]``: frame n of sample b is valid when ``n < lengths[b]``."""
    return torch.arange(N, device=lengths.device) < lengths.reshape(-1, 1)


def dense_loss(pred: torch.Tensor, target: torch.Tensor, lengths: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Per-sample MSE ``[B]`` over all valid frames. ``pred, target [B, N, D]``, ``lengths [B]``."""
    if pred.shape != target.shape or pred.dim() != 3:
        raise ValueError(f"dense_loss: pred and target must both be [B, N, D], got {tuple(pred.shape)} "
                         f"and {tuple(target.shape)}")
    B, N, _ = pred.shape
    m = torch.ones(B, N, dtype=torch.bool, device=pred.device) if lengths is None else valid_frames(
        torch.as_tensor(lengths, device=pred.device), N)
    return _masked_mean(pred, target, m)


def keyframe_loss(pred: torch.Tensor, target: torch.Tensor, keyframes: torch.Tensor) -> torch.Tensor:
    """Per-sample MSE ``[B]`` on keyframes only (the "w/o interpolation" ablation).
    ``keyframes [B, N]`` bool (non-keyframes and padding False)."""
    if keyframes.shape != pred.shape[:2]:
        raise ValueError(f"keyframe_loss: keyframes must be [B, N]={list(pred.shape[:2])}, got "
                         f"{list(keyframes.shape)}")
    return _masked_mean(pred, target, keyframes.to(torch.bool))


def _masked_mean(pred: torch.Tensor, target: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    err = ((pred - target) ** 2).mean(-1)  # [B, N]
    w = m.to(err.dtype)
    return (err * w).sum(1) / w.sum(1).clamp_min(1)


def lipschitz_term(model: nn.Module, lam: float) -> torch.Tensor:
    """``lam * ∏ softplus(c_i)`` summed over the model's Lipschitz MLPs (0 when there are none)."""
    return lam * lipschitz_loss(model)


def add_lipschitz_term(terms: dict, model: MLPs, config, batch: int) -> dict:
    """Add ``config.lipschitz_lambda * L_lip`` of ``model`` (a module, or its Lipschitz MLPs) to ``terms['loss']`` (or to
    ``terms['mse']`` when there is no ``loss``) and log it as ``terms['lip'] [batch]``; no-op when
    the Lipschitz layers are off or λ = 0. Returns ``terms``."""
    if not (config.enabled and config.lipschitz and config.lipschitz_lambda > 0):
        return terms
    lip = lipschitz_loss(model)
    terms["lip"] = lip.detach().expand(batch)
    terms["loss"] = terms.get("loss", terms.get("mse")) + config.lipschitz_lambda * lip
    return terms
