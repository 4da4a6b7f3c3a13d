"""``TinyMDM``: a small model with MDM's module names and ``forward(x, timesteps, y)`` contract.

It lets CI (which has no MDM checkout) run the adapter end to end and lets users try sparse mode
without upstream code. Written from scratch; only the interface follows MDM:

* ``x``: ``[B, njoints, nfeats, N]`` (HumanML3D: ``[B, 263, 1, N]``), ``timesteps``: ``[B]`` long;
* ``y``: ``mask [B, 1, 1, N]`` bool (valid frames), ``lengths [B]``, ``text_embed [1, B, clip_dim]``
  (cached text features; or ``text`` with a ``text_encoder`` callable), ``uncond`` (bool),
  ``prefix [B, njoints, nfeats, context_len]`` for DiP-style prefix completion.
"""
from __future__ import annotations

import math
from typing import Any, Callable, Dict, List, Optional

import torch
import torch.nn as nn


class SinusoidalPositions(nn.Module):
    """Adds fixed sinusoidal positions to ``[S, B, d]`` (buffer ``pe [max_len, 1, d]``)."""

    def __init__(self, d_model: int, dropout: float = 0.1, max_len: int = 5000) -> None:
        super().__init__()
        self.dropout = nn.Dropout(dropout)
        pos = torch.arange(max_len, dtype=torch.float32)[:, None]
        freq = torch.exp(torch.arange(0, d_model, 2, dtype=torch.float32) * (-math.log(10000.0) / d_model))
        table = torch.zeros(max_len, d_model)
        table[:, 0::2] = torch.sin(pos * freq)
        table[:, 1::2] = torch.cos(pos * freq)
        self.register_buffer("pe", table[:, None, :])

    def forward(self, seq: torch.Tensor) -> torch.Tensor:
        return self.dropout(seq + self.pe[: seq.shape[0]])


class TimestepEmbed(nn.Module):
    """Diffusion step -> ``[1, B, d]`` through the sinusoid table and a 2-layer MLP."""

    def __init__(self, latent_dim: int, positions: SinusoidalPositions) -> None:
        super().__init__()
        self.sequence_pos_encoder = positions
        self.time_embed = nn.Sequential(nn.Linear(latent_dim, latent_dim), nn.SiLU(),
                                        nn.Linear(latent_dim, latent_dim))

    def forward(self, timesteps: torch.Tensor) -> torch.Tensor:
        return self.time_embed(self.sequence_pos_encoder.pe[timesteps.long()]).permute(1, 0, 2)


class PoseIn(nn.Module):
    """``[B, J, F, N]`` -> ``[N, B, d]``."""

    def __init__(self, input_feats: int, latent_dim: int) -> None:
        super().__init__()
        self.poseEmbedding = nn.Linear(input_feats, latent_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, J, F_, N = x.shape
        return self.poseEmbedding(x.permute(3, 0, 1, 2).reshape(N, B, J * F_))


class PoseOut(nn.Module):
    """``[N, B, d]`` -> ``[B, J, F, N]``."""

    def __init__(self, latent_dim: int, njoints: int, nfeats: int) -> None:
        super().__init__()
        self.njoints, self.nfeats = njoints, nfeats
        self.poseFinal = nn.Linear(latent_dim, njoints * nfeats)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        N, B, _ = h.shape
        return self.poseFinal(h).reshape(N, B, self.njoints, self.nfeats).permute(1, 2, 3, 0)


class TinyMDM(nn.Module):
    """MDM-compatible denoiser (x0 prediction). Defaults: MDM's HumanML3D size is
    ``latent_dim=512, num_layers=8, num_heads=4, ff_size=1024``."""

    def __init__(self, njoints: int = 263, nfeats: int = 1, latent_dim: int = 256, ff_size: int = 1024,
                 num_layers: int = 4, num_heads: int = 4, dropout: float = 0.1, activation: str = "gelu",
                 arch: str = "trans_enc", emb_trans_dec: bool = False, cond_mode: str = "text",
                 clip_dim: int = 512, cond_mask_prob: float = 0.1, mask_frames: bool = True,
                 context_len: int = 0, pred_len: int = 0, max_len: int = 5000,
                 text_encoder: Optional[Callable[[List[str]], torch.Tensor]] = None) -> None:
        super().__init__()
        if arch not in ("trans_enc", "trans_dec"):
            raise ValueError(f"TinyMDM: arch must be 'trans_enc' or 'trans_dec', got {arch!r}")
        if cond_mode not in ("text", "no_cond"):
            raise ValueError(f"TinyMDM: cond_mode must be 'text' or 'no_cond', got {cond_mode!r}")
        self.njoints, self.nfeats, self.latent_dim = njoints, nfeats, latent_dim
        self.arch, self.emb_trans_dec, self.cond_mode = arch, emb_trans_dec, cond_mode
        self.cond_mask_prob, self.mask_frames, self.clip_dim = cond_mask_prob, mask_frames, clip_dim
        self.context_len, self.pred_len = context_len, pred_len
        self.is_prefix_comp = context_len > 0
        self.text_encoder = text_encoder
        self.input_process = PoseIn(njoints * nfeats, latent_dim)
        self.sequence_pos_encoder = SinusoidalPositions(latent_dim, dropout, max_len)
        self.embed_timestep = TimestepEmbed(latent_dim, self.sequence_pos_encoder)
        if cond_mode == "text":
            self.embed_text = nn.Linear(clip_dim, latent_dim)
        if arch == "trans_enc":
            layer = nn.TransformerEncoderLayer(latent_dim, num_heads, ff_size, dropout, activation)
            self.seqTransEncoder = nn.TransformerEncoder(layer, num_layers, enable_nested_tensor=False)
        else:
            layer = nn.TransformerDecoderLayer(latent_dim, num_heads, ff_size, dropout, activation)
            self.seqTransDecoder = nn.TransformerDecoder(layer, num_layers)
        self.output_process = PoseOut(latent_dim, njoints, nfeats)

    def parameters_wo_clip(self) -> List[nn.Parameter]:
        return [p for n, p in self.named_parameters() if not n.startswith("clip_model.")]

    def _condition(self, y: Dict[str, Any], B: int, device: torch.device) -> Optional[torch.Tensor]:
        if self.cond_mode != "text":
            return None
        if "text_embed" in y:
            enc = y["text_embed"]
            enc = enc.unsqueeze(0) if enc.dim() == 2 else enc
        elif self.text_encoder is not None and "text" in y:
            enc = self.text_encoder(y["text"]).reshape(1, B, self.clip_dim)
        else:
            enc = torch.zeros(1, B, self.clip_dim, device=device)
        enc = enc.to(device)
        if y.get("uncond", False):
            enc = torch.zeros_like(enc)
        elif self.training and self.cond_mask_prob > 0:
            keep = torch.rand(B, device=device) >= self.cond_mask_prob
            enc = enc * keep.view(1, B, 1).to(enc.dtype)
        return self.embed_text(enc)

    def forward(self, x: torch.Tensor, timesteps: torch.Tensor, y: Optional[Dict[str, Any]] = None
                ) -> torch.Tensor:
        y = y if y is not None else {}
        B = x.shape[0]
        time_emb = self.embed_timestep(timesteps)  # [1, B, d]
        text = self._condition(y, B, x.device)
        emb = time_emb if text is None else time_emb + text
        valid = y.get("mask")
        if self.is_prefix_comp:
            x = torch.cat([y["prefix"], x], dim=-1)
            if isinstance(valid, torch.Tensor) and valid.shape[-1] > 1:
                valid = torch.cat([valid.new_ones(B, 1, 1, self.context_len), valid], dim=-1)
        N = x.shape[-1]
        h = self.input_process(x)  # [N, B, d]
        pad = None
        if self.mask_frames and isinstance(valid, torch.Tensor) and valid.shape[-1] == N:
            pad = ~valid.reshape(B, N).to(torch.bool)
        if self.arch == "trans_enc":
            seq = self.sequence_pos_encoder(torch.cat([emb, h], dim=0))
            if pad is not None:
                pad = torch.cat([pad.new_zeros(B, 1), pad], dim=1)
            out = self.seqTransEncoder(seq, src_key_padding_mask=pad)[1:]
        else:
            lead = 1 if self.emb_trans_dec else 0
            seq = torch.cat([time_emb, h], dim=0) if lead else h
            seq = self.sequence_pos_encoder(seq)
            if pad is not None and lead:
                pad = torch.cat([pad.new_zeros(B, 1), pad], dim=1)
            out = self.seqTransDecoder(tgt=seq, memory=emb, tgt_key_padding_mask=pad)[lead:]
        if self.is_prefix_comp:
            out = out[self.context_len:]
        return self.output_process(out)
