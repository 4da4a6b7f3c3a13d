"""``MotionDiffuseDenoiser``: a denoiser with MotionDiffuse's *interface*, written here."""
from __future__ import annotations

from typing import List, Optional, Sequence, Tuple

import torch
import torch.nn as nn

from .embedding import timestep_embedding

__all__ = ["MotionDiffuseDenoiser", "timestep_embedding", "motiondiffuse_size"]

#: added to the keys of padded frames before their softmax over the frames (they get ~0 weight)
_PAD_LOGIT = -1.0e6


def motiondiffuse_size(quick: bool = False) -> dict:
    """MotionDiffuse's HumanML3D size (latent 512, 8 layers, 8 heads, FFN 1024, text 256), or a
    tiny one for smoke runs."""
    if quick:
        return dict(latent_dim=64, ff_size=128, num_layers=2, num_heads=4, text_latent_dim=32)
    return dict(latent_dim=512, ff_size=1024, num_layers=8, num_heads=8, text_latent_dim=256)


def linear_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, heads: int,
                     drop: nn.Module) -> torch.Tensor:
    """Softmax-kernel linear attention: ``q [B, T, C]``, ``k, v [B, S, C]`` -> ``[B, T, C]``.
    Per head, queries are normalised over their channels and keys over the ``S`` tokens; the
    output is ``q · (kᵀ · v)`` (cost linear in ``T`` and ``S``)."""
    B, T, C = q.shape
    S = k.shape[1]
    qh = q.reshape(B, T, heads, C // heads).softmax(dim=-1).transpose(1, 2)        # [B, H, T, c]
    kh = drop(k.reshape(B, S, heads, C // heads).softmax(dim=1)).permute(0, 2, 3, 1)  # [B, H, c, S]
    vh = v.reshape(B, S, heads, C // heads).transpose(1, 2)                      # [B, H, S, c]
    return torch.matmul(qh, torch.matmul(kh, vh)).transpose(1, 2).reshape(B, T, C)


class StepModulation(nn.Module):
    """``proj(norm(h) · (1 + a) + b)``, ``(a, b)`` from the step embedding; ``proj`` starts at 0,
    so a fresh sub-layer adds nothing to its input."""

    def __init__(self, width: int, emb_width: int, dropout: float) -> None:
        super().__init__()
        self.to_scale_shift = nn.Linear(emb_width, 2 * width)
        self.norm = nn.LayerNorm(width)
        self.proj = nn.Linear(width, width)
        self.drop = nn.Dropout(dropout)
        nn.init.zeros_(self.proj.weight)
        nn.init.zeros_(self.proj.bias)

    def forward(self, h: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        """``h [B, T, width]``, ``emb [B, emb_width]``."""
        a, b = self.to_scale_shift(nn.functional.silu(emb))[:, None].chunk(2, dim=-1)
        return self.proj(self.drop(nn.functional.silu(self.norm(h) * (1 + a) + b)))


class DenoiserBlock(nn.Module):
    """Frames attend to themselves, then to the text, then a feed-forward; each step-modulated and
    residual. ``forward(h [B, T, w], xf [B, L, text], emb [B, e], src_mask [B, T, 1] float)``."""

    def __init__(self, width: int, text_width: int, emb_width: int, ff_width: int, heads: int,
                 dropout: float) -> None:
        super().__init__()
        self.heads = heads
        self.frame_norm = nn.LayerNorm(width)
        self.frame_qkv = nn.Linear(width, 3 * width)
        self.text_q_norm = nn.LayerNorm(width)
        self.text_norm = nn.LayerNorm(text_width)
        self.text_q = nn.Linear(width, width)
        self.text_kv = nn.Linear(text_width, 2 * width)
        self.ff = nn.Sequential(nn.Linear(width, ff_width), nn.GELU(), nn.Dropout(dropout),
                                nn.Linear(ff_width, width))
        nn.init.zeros_(self.ff[-1].weight)
        nn.init.zeros_(self.ff[-1].bias)
        self.drop = nn.Dropout(dropout)
        self.mod = nn.ModuleList(StepModulation(width, emb_width, dropout) for _ in range(3))

    def forward(self, h: torch.Tensor, xf: torch.Tensor, emb: torch.Tensor, src_mask: torch.Tensor) -> torch.Tensor:
        q, k, v = self.frame_qkv(self.frame_norm(h)).chunk(3, dim=-1)
        k = k + (1 - src_mask) * _PAD_LOGIT                      # padded frames: no weight
        h = h + self.mod[0](linear_attention(q, k, v * src_mask, self.heads, self.drop), emb)
        tk, tv = self.text_kv(self.text_norm(xf)).chunk(2, dim=-1)
        h = h + self.mod[1](linear_attention(self.text_q(self.text_q_norm(h)), tk, tv, self.heads, self.drop), emb)
        return h + self.mod[2](self.ff(h), emb)


class MotionDiffuseDenoiser(nn.Module):
    """A denoiser with MotionDiffuse's interface (see the module docstring). Defaults: HumanML3D
    (263 features, up to 196 frames) at :func:`motiondiffuse_size`."""

    def __init__(self, input_feats: int = 263, num_frames: int = 196, latent_dim: int = 512, ff_size: int = 1024,
                 num_layers: int = 8, num_heads: int = 8, dropout: float = 0.0, text_latent_dim: int = 256,
                 text_vocab: int = 64) -> None:
        super().__init__()
        if latent_dim % num_heads:
            raise ValueError(f"MotionDiffuseDenoiser: latent_dim={latent_dim} must be a multiple of "
                             f"num_heads={num_heads}")
        self.input_feats, self.num_frames, self.latent_dim = input_feats, num_frames, latent_dim
        self.num_layers, self.num_heads, self.text_latent_dim = num_layers, num_heads, text_latent_dim
        emb_width = 4 * latent_dim
        self.sequence_embedding = nn.Parameter(torch.randn(num_frames, latent_dim))
        self.char_table = nn.Embedding(text_vocab, text_latent_dim)      # the stand-in text encoder
        self.char_norm = nn.LayerNorm(text_latent_dim)
        self.text_to_emb = nn.Linear(text_latent_dim, emb_width)
        self.joint_embed = nn.Linear(input_feats, latent_dim)
        self.time_embed = nn.Sequential(nn.Linear(latent_dim, emb_width), nn.SiLU(), nn.Linear(emb_width, emb_width))
        self.temporal_decoder_blocks = nn.ModuleList(
            DenoiserBlock(latent_dim, text_latent_dim, emb_width, ff_size, num_heads, dropout) for _ in range(num_layers))
        self.out = nn.Linear(latent_dim, input_feats)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def encode_text(self, text: Sequence[str], device: torch.device, length: int = 16
                    ) -> Tuple[torch.Tensor, torch.Tensor]:
        """``(xf_proj [B, 4·latent], xf_out [B, length, text_latent])`` from captions: their first
        ``length`` characters, each looked up in a learned table (a stand-in for a text encoder)."""
        vocab = self.char_table.num_embeddings
        ids = torch.tensor([[ord(c) % vocab for c in s.ljust(length)[:length]] for s in text], device=device)
        tokens = self.char_norm(self.char_table(ids))
        return self.text_to_emb(tokens.mean(dim=1)), tokens

    def forward(self, x: torch.Tensor, timesteps: torch.Tensor, length: Optional[torch.Tensor] = None,
                text: Optional[List[str]] = None, xf_proj: Optional[torch.Tensor] = None,
                xf_out: Optional[torch.Tensor] = None) -> torch.Tensor:
        """``x [B, T, D]`` noisy motion, ``timesteps [B]``, ``length [B]`` valid frames (None = all)
        -> ``[B, T, D]``."""
        B, T = x.shape[0], x.shape[1]
        if xf_proj is None or xf_out is None:
            xf_proj, xf_out = self.encode_text(text, x.device)
        emb = self.time_embed(timestep_embedding(timesteps, self.latent_dim)) + xf_proj
        h = self.joint_embed(x) + self.sequence_embedding[:T]
        valid = torch.full((B,), T, device=x.device) if length is None else torch.as_tensor(length, device=x.device)
        src_mask = (torch.arange(T, device=x.device)[None] < valid.reshape(-1, 1)).to(h.dtype).unsqueeze(-1)
        for block in self.temporal_decoder_blocks:
            h = block(h, xf_out, emb, src_mask)
        return self.out(h)
