"""Held-out measures of a trained model that need its diffusion (``smdm ablate``'s ``val loss``)."""
from __future__ import annotations

import numpy as np
import torch

from ..reference.simple_diffusion import masked_mse
from .data import MotionSet


def validation_loss(model, diffusion, val: MotionSet, device: torch.device, seed: int, n_t: int = 5) -> float:
    """Denoising MSE on the motions of ``val`` over all valid frames, at ``n_t`` fixed timesteps
    spread over ``[0, T)`` with fixed noise (identical for every variant). The model runs as it
    would at sampling time (its own keyframe schedule on ``x_t``), so sparse and dense compare on
    the same dense frames. Not comparable with training losses, which sample t at random."""
    padded, lengths = val.padded()
    x = padded.permute(0, 2, 1).unsqueeze(2).to(device)
    B, N = x.shape[0], x.shape[-1]
    y = {"mask": (torch.arange(N) < lengths[:, None]).view(B, 1, 1, N).to(device), "lengths": lengths.to(device)}
    g = torch.Generator().manual_seed(seed + 4)
    out = []
    with torch.no_grad():
        for t in torch.linspace(0, diffusion.num_timesteps - 1, n_t).round().long():
            tt = t.expand(B).to(device)
            noise = torch.randn(x.shape, generator=g).to(device)
            pred = model(diffusion.q_sample(x, tt, noise), tt, {"y": dict(y)})
            out.append(float(masked_mse(pred, x, y["mask"]).mean()))
    return float(np.mean(out))
