"""A stand-in with MotionDiffuse's ``MotionTransformer`` attribute names and forward contract,
written here from scratch (CI has no MotionDiffuse checkout); shared by the MotionDiffuse tests and
the family conformance suite."""
import math

import torch
import torch.nn as nn
import torch.nn.functional as F


# --------------------------------------------------------------------------- stand-in model
def sinusoid(t, dim):
    half = dim // 2
    f = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32) / half)
    a = t.float()[:, None] * f[None]
    return torch.cat([a.cos(), a.sin()], -1)


class Modulate(nn.Module):
    def __init__(self, d, e):
        super().__init__()
        self.emb_layers = nn.Sequential(nn.SiLU(), nn.Linear(e, 2 * d))
        self.norm = nn.LayerNorm(d)
        self.out_layers = nn.Sequential(nn.SiLU(), nn.Linear(d, d))

    def forward(self, h, emb):
        s, b = self.emb_layers(emb)[:, None].chunk(2, -1)
        return self.out_layers(self.norm(h) * (1 + s) + b)


class LinSelfAttn(nn.Module):
    """Linear (softmax-kernel) attention whose padded tokens are masked through ``src_mask``."""

    def __init__(self, d, heads, e):
        super().__init__()
        self.h = heads
        self.norm = nn.LayerNorm(d)
        self.query, self.key, self.value = nn.Linear(d, d), nn.Linear(d, d), nn.Linear(d, d)
        self.proj_out = Modulate(d, e)

    def forward(self, x, emb, src_mask):
        B, T, D = x.shape
        n = self.norm(x)
        q = F.softmax(self.query(n).view(B, T, self.h, -1), -1)
        k = F.softmax((self.key(n) - (1 - src_mask) * 1e6).view(B, T, self.h, -1), 1)
        v = (self.value(n) * src_mask).view(B, T, self.h, -1)
        ctx = torch.einsum("bthd,bthe->bhde", k, v)
        return x + self.proj_out(torch.einsum("bthd,bhde->bthe", q, ctx).reshape(B, T, D), emb)


class CrossAttn(nn.Module):
    def __init__(self, d, dt, heads, e):
        super().__init__()
        self.h = heads
        self.q, self.kv = nn.Linear(d, d), nn.Linear(dt, 2 * d)
        self.proj_out = Modulate(d, e)

    def forward(self, x, xf, emb):
        B, T, D = x.shape
        k, v = self.kv(xf).chunk(2, -1)
        w = torch.softmax(self.q(x) @ k.transpose(1, 2) / math.sqrt(D), -1)
        return x + self.proj_out(w @ v, emb)


class Block(nn.Module):
    def __init__(self, d, dt, heads, e):
        super().__init__()
        self.sa_block = LinSelfAttn(d, heads, e)
        self.ca_block = CrossAttn(d, dt, heads, e)
        self.ffn = nn.Sequential(nn.Linear(d, 2 * d), nn.GELU(), nn.Linear(2 * d, d))

    def forward(self, x, xf, emb, src_mask):
        x = self.sa_block(x, emb, src_mask)
        x = self.ca_block(x, xf, emb)
        return x + self.ffn(x)


class StandInMotionTransformer(nn.Module):
    """Same attribute names and ``forward(x, timesteps, length, text, xf_proj, xf_out)`` contract
    as MotionDiffuse's MotionTransformer; the text encoder is a bag of hashed characters."""

    def __init__(self, input_feats=12, num_frames=40, latent_dim=32, num_layers=2, text_dim=16):
        super().__init__()
        self.input_feats, self.num_frames, self.latent_dim = input_feats, num_frames, latent_dim
        self.time_embed_dim = 4 * latent_dim
        self.sequence_embedding = nn.Parameter(torch.randn(num_frames, latent_dim))
        self.char_embed = nn.Embedding(64, text_dim)
        self.text_proj = nn.Linear(text_dim, self.time_embed_dim)
        self.joint_embed = nn.Linear(input_feats, latent_dim)
        self.time_embed = nn.Sequential(nn.Linear(latent_dim, self.time_embed_dim), nn.SiLU(),
                                        nn.Linear(self.time_embed_dim, self.time_embed_dim))
        self.temporal_decoder_blocks = nn.ModuleList(
            Block(latent_dim, text_dim, 4, self.time_embed_dim) for _ in range(num_layers))
        self.out = nn.Linear(latent_dim, input_feats)

    def encode_text(self, text, device):
        ids = torch.tensor([[ord(c) % 64 for c in (s + " " * 8)[:8]] for s in text], device=device)
        xf_out = self.char_embed(ids)
        return self.text_proj(xf_out.mean(1)), xf_out

    def generate_src_mask(self, T, length):
        return (torch.arange(T)[None] < torch.as_tensor(length).reshape(-1, 1)).float()

    def forward(self, x, timesteps, length=None, text=None, xf_proj=None, xf_out=None):
        B, T = x.shape[:2]
        if xf_proj is None or xf_out is None:
            xf_proj, xf_out = self.encode_text(text, x.device)
        emb = self.time_embed(sinusoid(timesteps, self.latent_dim)) + xf_proj
        h = self.joint_embed(x) + self.sequence_embedding[None, :T]
        src_mask = self.generate_src_mask(T, length).to(x.device).unsqueeze(-1)
        for blk in self.temporal_decoder_blocks:
            h = blk(h, xf_out, emb, src_mask)
        return self.out(h).view(B, T, -1).contiguous()


class StandInDiffusion:
    """``training_losses`` with MotionDiffuse's contract: returns target/pred and an unmasked
    ``mse`` over all frames."""

    num_timesteps = 50

    def training_losses(self, model, x_start, t, model_kwargs=None, noise=None):
        noise = torch.randn_like(x_start) if noise is None else noise
        x_t = x_start * 0.5 + noise * 0.5
        pred = model(x_t, t, **(model_kwargs or {}))
        return {"mse": ((noise - pred) ** 2).mean(dim=(1, 2)), "target": noise, "pred": pred}
