"""``MotionTransformer``: a model with MotionDiffuse's denoiser layout, written from scratch.

So that the MotionDiffuse family (``smdm_plugin.adapters.motiondiffuse``) runs without an upstream
checkout (``smdm bench --family motiondiffuse``, tests). It has the attribute names and the
``forward(x [B, T, D], timesteps [B], length, text, xf_proj, xf_out) -> [B, T, D]`` contract of
MotionDiffuse's ``text2motion/models/transformer.py`` and the same computation per block:

* ``joint_embed`` (Linear ``D -> latent``) + the learned per-frame ``sequence_embedding``;
* the step embedding: ``time_embed(timestep_embedding(t, latent)) + xf_proj`` (``[B, 4·latent]``);
* ``temporal_decoder_blocks``: linear self-attention (softmax over the feature axis for queries,
  over frames for keys; padded frames masked through ``src_mask [B, T, 1]``), linear
  cross-attention to the text features ``xf_out [B, L, text_latent]``, a GELU FFN; each followed by
  a stylization block (LayerNorm modulated by the step embedding, zero-initialised output) and a
  residual;
* ``out`` (Linear ``latent -> D``).

Where it differs: the text encoder. ``encode_text`` is a bag of hashed characters (no CLIP, no
text transformer); benchmarks pass precomputed ``xf_proj`` / ``xf_out`` as MotionDiffuse's own
sampling does once per prompt. ``generate_src_mask`` is one vectorised comparison (upstream loops
over samples and frames on the host; that would only slow the dense model down).
"""
from __future__ import annotations

from typing import List, Optional, Sequence, Tuple

import torch
import torch.nn as nn
import torch.nn.functional as F

from ..core.embedding import timestep_embedding

__all__ = ["MotionTransformer", "timestep_embedding", "motiondiffuse_size"]


def motiondiffuse_size(quick: bool = False) -> dict:
    """MotionDiffuse's HumanML3D size (latent 512, 8 layers, 8 heads, FFN 1024, text 256), or a
    tiny one for smoke runs."""
    if quick:
        return dict(latent_dim=64, ff_size=128, num_layers=2, num_heads=4, text_latent_dim=32)
    return dict(latent_dim=512, ff_size=1024, num_layers=8, num_heads=8, text_latent_dim=256)


def _zero(module: nn.Linear) -> nn.Linear:
    nn.init.zeros_(module.weight)
    nn.init.zeros_(module.bias)
    return module


class StylizationBlock(nn.Module):
    """``out_layers(norm(h) * (1 + scale) + shift)`` with ``scale, shift`` from the step embedding."""

    def __init__(self, latent_dim: int, time_embed_dim: int, dropout: float) -> None:
        super().__init__()
        self.emb_layers = nn.Sequential(nn.SiLU(), nn.Linear(time_embed_dim, 2 * latent_dim))
        self.norm = nn.LayerNorm(latent_dim)
        self.out_layers = nn.Sequential(nn.SiLU(), nn.Dropout(dropout), _zero(nn.Linear(latent_dim, latent_dim)))

    def forward(self, h: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        """``h [B, T, latent]``, ``emb [B, time_embed_dim]``."""
        scale, shift = self.emb_layers(emb).unsqueeze(1).chunk(2, dim=2)
        return self.out_layers(self.norm(h) * (1 + scale) + shift)


class LinearTemporalSelfAttention(nn.Module):
    def __init__(self, latent_dim: int, num_head: int, dropout: float, time_embed_dim: int) -> None:
        super().__init__()
        self.num_head = num_head
        self.norm = nn.LayerNorm(latent_dim)
        self.query, self.key, self.value = (nn.Linear(latent_dim, latent_dim) for _ in range(3))
        self.dropout = nn.Dropout(dropout)
        self.proj_out = StylizationBlock(latent_dim, time_embed_dim, dropout)

    def forward(self, x: torch.Tensor, emb: torch.Tensor, src_mask: torch.Tensor) -> torch.Tensor:
        """``x [B, T, latent]``, ``src_mask [B, T, 1]`` float (1 = a frame, 0 = padding)."""
        B, T, D = x.shape
        H = self.num_head
        n = self.norm(x)
        query = F.softmax(self.query(n).view(B, T, H, -1), dim=-1)
        key = F.softmax((self.key(n) + (1 - src_mask) * -1000000).view(B, T, H, -1), dim=1)
        value = (self.value(n) * src_mask).view(B, T, H, -1)
        attention = torch.einsum("bnhd,bnhl->bhdl", self.dropout(key), value)
        y = torch.einsum("bnhd,bhdl->bnhl", query, attention).reshape(B, T, D)
        return x + self.proj_out(y, emb)


class LinearTemporalCrossAttention(nn.Module):
    def __init__(self, latent_dim: int, text_latent_dim: int, num_head: int, dropout: float,
                 time_embed_dim: int) -> None:
        super().__init__()
        self.num_head = num_head
        self.norm = nn.LayerNorm(latent_dim)
        self.text_norm = nn.LayerNorm(text_latent_dim)
        self.query = nn.Linear(latent_dim, latent_dim)
        self.key = nn.Linear(text_latent_dim, latent_dim)
        self.value = nn.Linear(text_latent_dim, latent_dim)
        self.dropout = nn.Dropout(dropout)
        self.proj_out = StylizationBlock(latent_dim, time_embed_dim, dropout)

    def forward(self, x: torch.Tensor, xf: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        """``x [B, T, latent]``, ``xf [B, L, text_latent]``."""
        B, T, D = x.shape
        L, H = xf.shape[1], self.num_head
        query = F.softmax(self.query(self.norm(x)).view(B, T, H, -1), dim=-1)
        tf = self.text_norm(xf)
        key = F.softmax(self.key(tf).view(B, L, H, -1), dim=1)
        value = self.value(tf).view(B, L, H, -1)
        attention = torch.einsum("bnhd,bnhl->bhdl", self.dropout(key), value)
        y = torch.einsum("bnhd,bhdl->bnhl", query, attention).reshape(B, T, D)
        return x + self.proj_out(y, emb)


class FFN(nn.Module):
    def __init__(self, latent_dim: int, ffn_dim: int, dropout: float, time_embed_dim: int) -> None:
        super().__init__()
        self.linear1 = nn.Linear(latent_dim, ffn_dim)
        self.linear2 = _zero(nn.Linear(ffn_dim, latent_dim))
        self.activation = nn.GELU()
        self.dropout = nn.Dropout(dropout)
        self.proj_out = StylizationBlock(latent_dim, time_embed_dim, dropout)

    def forward(self, x: torch.Tensor, emb: torch.Tensor) -> torch.Tensor:
        return x + self.proj_out(self.linear2(self.dropout(self.activation(self.linear1(x)))), emb)


class TemporalDiffusionTransformerDecoderLayer(nn.Module):
    """Self-attention, cross-attention to the text, FFN: ``forward(x, xf, emb, src_mask)``."""

    def __init__(self, latent_dim: int, text_latent_dim: int, time_embed_dim: int, ffn_dim: int,
                 num_head: int, dropout: float) -> None:
        super().__init__()
        self.sa_block = LinearTemporalSelfAttention(latent_dim, num_head, dropout, time_embed_dim)
        self.ca_block = LinearTemporalCrossAttention(latent_dim, text_latent_dim, num_head, dropout, time_embed_dim)
        self.ffn = FFN(latent_dim, ffn_dim, dropout, time_embed_dim)

    def forward(self, x: torch.Tensor, xf: torch.Tensor, emb: torch.Tensor, src_mask: torch.Tensor) -> torch.Tensor:
        return self.ffn(self.ca_block(self.sa_block(x, emb, src_mask), xf, emb), emb)


class MotionTransformer(nn.Module):
    """MotionDiffuse's denoiser layout (see the module docstring). Defaults: HumanML3D
    (263 features, up to 196 frames) at :func:`motiondiffuse_size`."""

    def __init__(self, input_feats: int = 263, num_frames: int = 196, latent_dim: int = 512, ff_size: int = 1024,
                 num_layers: int = 8, num_heads: int = 8, dropout: float = 0.0, text_latent_dim: int = 256,
                 text_vocab: int = 64) -> None:
        super().__init__()
        self.input_feats, self.num_frames, self.latent_dim = input_feats, num_frames, latent_dim
        self.num_layers, self.num_heads, self.text_latent_dim = num_layers, num_heads, text_latent_dim
        self.time_embed_dim = 4 * latent_dim
        self.sequence_embedding = nn.Parameter(torch.randn(num_frames, latent_dim))
        self.token_embedding = nn.Embedding(text_vocab, text_latent_dim)   # the stand-in text encoder
        self.text_ln = nn.LayerNorm(text_latent_dim)
        self.text_proj = nn.Linear(text_latent_dim, self.time_embed_dim)
        self.joint_embed = nn.Linear(input_feats, latent_dim)
        self.time_embed = nn.Sequential(nn.Linear(latent_dim, self.time_embed_dim), nn.SiLU(),
                                        nn.Linear(self.time_embed_dim, self.time_embed_dim))
        self.temporal_decoder_blocks = nn.ModuleList(
            TemporalDiffusionTransformerDecoderLayer(latent_dim, text_latent_dim, self.time_embed_dim, ff_size,
                                                     num_heads, dropout) for _ in range(num_layers))
        self.out = _zero(nn.Linear(latent_dim, input_feats))

    def encode_text(self, text: Sequence[str], device: torch.device, length: int = 16
                    ) -> Tuple[torch.Tensor, torch.Tensor]:
        """``(xf_proj [B, 4·latent], xf_out [B, length, text_latent])`` from captions: their first
        ``length`` characters, hashed into a learned table (a stand-in for CLIP + the text layers)."""
        vocab = self.token_embedding.num_embeddings
        ids = torch.tensor([[ord(c) % vocab for c in (s + " " * length)[:length]] for s in text], device=device)
        xf_out = self.text_ln(self.token_embedding(ids))
        return self.text_proj(xf_out.mean(1)), xf_out

    def generate_src_mask(self, T: int, length: torch.Tensor) -> torch.Tensor:
        """float ``[B, T]``: 1 for the first ``length[b]`` frames."""
        length = torch.as_tensor(length).reshape(-1, 1)
        return (torch.arange(T, device=length.device)[None] < length).float()

    def forward(self, x: torch.Tensor, timesteps: torch.Tensor, length: Optional[torch.Tensor] = None,
                text: Optional[List[str]] = None, xf_proj: Optional[torch.Tensor] = None,
                xf_out: Optional[torch.Tensor] = None) -> torch.Tensor:
        """``x [B, T, D]`` noisy motion, ``timesteps [B]``, ``length [B]`` valid frames (None = all)
        -> ``[B, T, D]``."""
        B, T = x.shape[0], x.shape[1]
        if xf_proj is None or xf_out is None:
            xf_proj, xf_out = self.encode_text(text, x.device)
        emb = self.time_embed(timestep_embedding(timesteps, self.latent_dim)) + xf_proj
        h = self.joint_embed(x) + self.sequence_embedding.unsqueeze(0)[:, :T, :]
        length = torch.full((B,), T, device=x.device) if length is None else length
        src_mask = self.generate_src_mask(T, length).to(x.device).unsqueeze(-1)
        for module in self.temporal_decoder_blocks:
            h = module(h, xf_out, emb, src_mask)
        return self.out(h).view(B, T, -1).contiguous()
