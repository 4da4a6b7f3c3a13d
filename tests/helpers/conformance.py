"""The conformance cases of the model families (tests/adapters/test_family_conformance.py): how to build a
model of a family, its diffusion, its inputs, call it and take its loss.

Every registered family (``smdm_plugin.adapters.families.FAMILIES``) is mapped here to a case factory:
``CASE_FACTORIES[family name]() -> [case, ...]`` (one case per variant worth checking). A family registered
without one fails ``test_every_registered_family_has_a_conformance_case``: whoever adds a family adds its
cases with :func:`register_cases`.
"""
from __future__ import annotations

from typing import Callable, Dict, List

import torch

from smdm_plugin import SimpleDiffusion, SparseConfig, TinyMDM
from smdm_plugin.adapters.families import families

from helpers.motiondiffuse_standin import StandInDiffusion, StandInMotionTransformer

STEPS = torch.tensor([1, 30, 45])   # made once: a tensor from host data is a host-to-device copy


class DoubleTakeTinyMDM(TinyMDM):
    """priorMDM's doubleTake_MDM is an MDM subclass; the family is recognised by the class name."""


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


#: family name -> the factory of its conformance cases
CASE_FACTORIES: Dict[str, Callable[[], List[object]]] = {}


def register_cases(family: str):
    """Decorator: ``factory() -> [case, ...]`` is the conformance cases of the family named ``family``."""
    def deco(factory: Callable[[], List[object]]):
        if family in CASE_FACTORIES:
            raise ValueError(f"conformance cases of family {family!r} are already registered")
        CASE_FACTORIES[family] = factory
        return factory
    return deco


@register_cases("mdm")
def _mdm_cases():
    return [MDMCase("mdm-trans_enc", "mdm", arch="trans_enc"),
            MDMCase("mdm-trans_dec", "mdm", arch="trans_dec"),
            MDMCase("dip", "mdm", arch="trans_dec", emb_trans_dec=True, context_len=20, pred_len=40)]


@register_cases("doubletake")
def _doubletake_cases():
    return [MDMCase("doubletake", "doubletake", cls=DoubleTakeTinyMDM, arch="trans_enc")]


@register_cases("motiondiffuse")
def _motiondiffuse_cases():
    return [MotionDiffuseCase()]


def families_without_cases() -> List[str]:
    """The registered families (registry order) that have no conformance case factory."""
    return [f.name for f in families() if f.name not in CASE_FACTORIES]


def conformance_cases() -> Dict[str, object]:
    """Case name -> case, for every registered family that has a factory (registry order)."""
    cases: Dict[str, object] = {}
    for fam in families():
        for case in CASE_FACTORIES.get(fam.name, lambda: [])():
            if case.name in cases:
                raise ValueError(f"two conformance cases are named {case.name!r}")
            cases[case.name] = case
    return cases


def assert_every_family_has_cases() -> None:
    """An ``AssertionError`` naming every registered family without a conformance case factory."""
    missing = families_without_cases()
    assert not missing, (f"registered model famil{'y' if len(missing) == 1 else 'ies'} without a conformance case: "
                         f"{', '.join(missing)} (add a case factory with helpers.conformance.register_cases)")
