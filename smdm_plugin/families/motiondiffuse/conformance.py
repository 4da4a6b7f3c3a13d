"""The ``motiondiffuse`` family's conformance case (``FamilySpec.conformance``): the stand-in of
``standin.py`` (MotionDiffuse's ``MotionTransformer`` names and forward contract)."""
from __future__ import annotations

import torch

from ...core.config import SparseConfig
from ..mdm.conformance import STEPS
from .standin import StandInDiffusion, StandInMotionTransformer


class MotionDiffuseCase:
    """The stand-in MotionTransformer: ``forward(x [B, T, D], t, length, text, xf_proj, xf_out)``."""

    name, family = "motiondiffuse", "motiondiffuse"

    def build(self):
        torch.manual_seed(0)
        return StandInMotionTransformer()

    def diffusion(self):
        return StandInDiffusion()

    def config(self, **kw):
        return SparseConfig(**{"reduction": 0.8, "dynamic_update": True, "feature": "raw", "fsq": False, **kw})

    def inputs(self, seed=0):
        g = torch.Generator().manual_seed(seed)
        text = torch.randn(3, 8, 16, generator=g)             # precomputed text features (xf_out)
        return torch.randn(3, 40, 12, generator=g), {"length": torch.tensor([40, 31, 17]), "xf_out": text}

    def _kw(self, model, y):
        xf_out = y["xf_out"]
        return {"length": y["length"], "xf_out": xf_out, "xf_proj": model.text_proj(xf_out.mean(1))}

    def valid(self, y):
        return torch.arange(40)[None] < y["length"][:, None]

    def call(self, model, x, t, y):
        return model(x, t, **self._kw(model, y))

    def out_frames(self, out):
        return out

    def loss(self, diffusion, model, x, y, seed=3):
        torch.manual_seed(seed)
        t = STEPS
        inner = getattr(model, "_orig_mod", model)
        terms = diffusion.training_losses(model, x, t, self._kw(inner, y), noise=torch.ones_like(x))
        w = self.valid(y).to(x.dtype)[..., None]
        return (((terms["pred"] - terms["target"]) ** 2) * w).sum() / w.sum()


def cases():
    return [MotionDiffuseCase()]
