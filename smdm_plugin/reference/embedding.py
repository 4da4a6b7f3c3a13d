"""The sinusoidal diffusion-step embedding MotionDiffuse's denoiser uses (cos half, then sin half)."""
from __future__ import annotations

import math

import torch


def timestep_embedding(timesteps: torch.Tensor, dim: int, max_period: int = 10000) -> torch.Tensor:
    """Sinusoidal embedding ``[B, dim]`` of diffusion steps ``timesteps [B]`` (cos half, then sin
    half; a zero column when ``dim`` is odd), as MotionDiffuse's ``MotionTransformer`` expects."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, dtype=torch.float32,
                                                           device=timesteps.device) / half)
    args = timesteps.reshape(-1, 1).float() * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    if dim % 2:
        emb = torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=-1)
    return emb
