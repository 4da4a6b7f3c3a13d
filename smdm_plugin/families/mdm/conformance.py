"""The ``mdm`` family's conformance cases (``FamilySpec.conformance``: the suite of
tests/adapters/test_family_conformance.py runs each): TinyMDM trans_enc, trans_dec and DiP (a dense
prefix); how to build the model, its diffusion, its inputs, call it and take its loss."""
from __future__ import annotations

import torch

from ...core.config import SparseConfig
from ...reference.backbone import TinyMDM
from ...reference.simple_diffusion import SimpleDiffusion

STEPS = torch.tensor([1, 30, 45])   # made once: a tensor from host data is a host-to-device copy


class MDMCase:
    """TinyMDM variants: ``forward(x [B, 263, 1, N], t, y)``; SimpleDiffusion's loss."""

    def __init__(self, name, family, cls=TinyMDM, **kw):
        self.name, self.family, self.cls, self.kw = name, family, cls, kw
        self.N = 40 if kw.get("context_len") else 48

    def build(self):
        torch.manual_seed(0)
        return self.cls(latent_dim=32, ff_size=64, num_layers=2, dropout=0.0, cond_mask_prob=0.0, **self.kw)

    def diffusion(self):
        return SimpleDiffusion(50)

    def config(self, **kw):
        return SparseConfig(**{"reduction": 0.8, "dynamic_update": True, **kw})

    def inputs(self, seed=0):
        g = torch.Generator().manual_seed(seed)
        B, N = 3, self.N
        lengths = torch.tensor([N, N - 7, N // 2]) if not self.kw.get("context_len") else torch.full((B,), N)
        y = {"mask": (torch.arange(N) < lengths[:, None]).view(B, 1, 1, N), "lengths": lengths,
             "text_embed": torch.randn(1, B, 512, generator=g)}
        if self.kw.get("context_len"):
            y["prefix"] = torch.randn(B, 263, 1, self.kw["context_len"], generator=g)
        return torch.randn(B, 263, 1, N, generator=g), y

    def valid(self, y):
        return y["mask"].reshape(y["mask"].shape[0], -1)

    def call(self, model, x, t, y):
        return model(x, t, dict(y))

    def out_frames(self, out):                       # [B, 263, 1, N] -> [B, N, 263]
        return out.squeeze(2).transpose(1, 2)

    def loss(self, diffusion, model, x, y, seed=3):
        torch.manual_seed(seed)
        t = STEPS
        return diffusion.training_losses(model, x, t, {"y": dict(y)}, noise=torch.ones_like(x))["loss"].mean()


def cases():
    return [MDMCase("mdm-trans_enc", "mdm", arch="trans_enc"),
            MDMCase("mdm-trans_dec", "mdm", arch="trans_dec"),
            MDMCase("dip", "mdm", arch="trans_dec", emb_trans_dec=True, context_len=20, pred_len=40)]
