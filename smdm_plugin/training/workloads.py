"""The benchmark workloads: how ``smdm bench`` builds, feeds and calls the in-package model of each
registered model family (:data:`~smdm_plugin.adapters.families.FAMILIES`).

One :class:`Workload` per family, registered in :data:`WORKLOADS` under the family's name (the
extension point: ``WORKLOADS.register("mymodel", MyWorkload())`` and ``smdm bench --family mymodel``
offers it). Built in: ``mdm`` (:class:`~smdm_plugin.reference.backbone.TinyMDM` at MDM's HumanML3D
size, ``trans_enc`` / ``trans_dec``, and on request DiP's prefix completion ``dip`` and priorMDM's
DoubleTake model ``doubletake``) and ``motiondiffuse`` (MotionDiffuse's denoiser layout, or
MotionDiffuse's own class from a checkout). :func:`build` makes the dense or sparse model and its
diffusion; :meth:`Workload.batch` a HumanML3D-like batch (:class:`WorkloadBatch`).
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import torch

from ..core.registry import Registry

__all__ = ["WorkloadBatch", "Workload", "MDMWorkload", "MotionDiffuseWorkload", "WORKLOADS", "FSQ_CHOICES",
           "family_choices", "build", "handshake_frames", "upstream_motion_transformer", "valid_lengths",
           "without_dropout"]

#: which side of the comparison gets FSQ-quantised attention keys (``build(fsq=)``, ``--fsq``)
FSQ_CHOICES = {"paper": "sparse only (dense = upstream MDM, sparse = the paper's recipe)",
               "both": "dense and sparse (like with like)", "off": "neither"}


@dataclass
class WorkloadBatch:
    """One benchmark batch: ``x`` the motion as the model takes it, ``frames [B, N, D]`` (what
    keyframe selection reads), ``lengths [B]`` (long, CPU) and ``kwargs`` the model's keyword
    arguments (copy them per call with :meth:`Workload.kwargs`: hooks may add keys);
    ``sampling``: what sampling calls add to them (DoubleTake's ``is_transition``)."""

    x: torch.Tensor
    frames: torch.Tensor
    lengths: torch.Tensor
    kwargs: Dict[str, Any]
    sampling: Dict[str, Any] = field(default_factory=dict)

    @property
    def size(self) -> int:
        """Motions in the batch."""
        return int(self.x.shape[0])


def valid_lengths(batch: int, frames: int, min_len: int, g: torch.Generator) -> torch.Tensor:
    """``[B]`` long valid lengths drawn in ``min_len..frames``; the first is ``frames`` (the longest
    sample sets the padded length)."""
    lengths = torch.randint(min(min_len, frames), frames + 1, (batch,), generator=g)
    lengths[0] = frames
    return lengths


class Workload:
    """How the benchmark builds, feeds and calls the in-package model of one registered model
    family. One subclass per family, registered in :data:`WORKLOADS` under the family's name;
    ``--family`` offers the registered families that have one. The sparse model is made with
    ``sparsify(..., family=name)``."""

    #: the model family's registered name
    family: str = ""
    #: the variants ``--arch`` chooses among
    archs: Tuple[str, ...] = ()
    #: the variants timed when ``--arch`` is left out
    default_archs: Tuple[str, ...] = ()
    #: whether FSQ-quantised attention keys apply (softmax attention)
    fsq: bool = True
    #: model calls per sampling step (2: classifier-free guidance)
    passes: int = 1
    #: the environment variable naming an upstream checkout (None: no upstream model to load)
    root_env: Optional[str] = None

    def size(self, quick: bool) -> Dict[str, int]:
        """The model's size keyword arguments (``quick``: a tiny model)."""
        raise NotImplementedError

    def model(self, arch: str, quick: bool, frames: int, root: Optional[str] = None) -> torch.nn.Module:
        """The dense model; ``root``: an upstream checkout to take the model class from (None =
        the in-package one)."""
        raise NotImplementedError

    def source(self, root: Optional[str]) -> str:
        """Where the model class comes from, as the table names it."""
        return "in-package"

    def check_root(self, root: str) -> None:
        """Raise ``ValueError`` (starting ``--root:``) unless ``root`` is a usable checkout."""
        raise ValueError(f"--root: --family {self.family} has no upstream model to load (leave it out)")

    def model_family(self, arch: str) -> str:
        """The registered model family ``sparsify`` makes variant ``arch`` sparse with."""
        return self.family

    def batch(self, batch: int, frames: int, device: torch.device, quick: bool,
              arch: Optional[str] = None, seed: int = 0) -> WorkloadBatch:
        """A HumanML3D-like batch of ``batch`` motions padded to ``frames`` (drawn with ``seed``) for
        variant ``arch`` (None: the first)."""
        raise NotImplementedError

    def kwargs(self, data: WorkloadBatch) -> Dict[str, Any]:
        """A fresh copy of the model keyword arguments (hooks may add keys to them)."""
        return dict(data.kwargs)

    def sample_kwargs(self, data: WorkloadBatch) -> Dict[str, Any]:
        """:meth:`kwargs` of a sampling call (with ``data.sampling``)."""
        return {**self.kwargs(data), **data.sampling}

    def denoiser(self, model: torch.nn.Module) -> torch.nn.Module:
        """What one sampling step calls: ``denoiser(x_t, t, **kwargs)``."""
        return model.eval()

    def call_args(self, data: WorkloadBatch, mask: torch.Tensor, capacity: int) -> Tuple[tuple, Dict[str, Any]]:
        """``(args, kwargs)`` of a model call with the given keyframes, as the family's ``read_call``
        reads them."""
        raise NotImplementedError

    def lead(self, model: torch.nn.Module) -> int:
        """Tokens before the frames in the keyframe transformer's sequence."""
        return 0

    def backend(self, backend: str, device: torch.device, compile_mode: str) -> str:
        """The sparse model's attention, as the table names it."""
        from ..core.attention_backends import resolve_backend_name

        return resolve_backend_name(backend, device) if compile_mode == "none" else "compact"


#: DiP's windows (its defaults at 20 fps): ``context_len`` prefix frames, then ``pred_len`` frames
DIP_CONTEXT, DIP_PRED = 20, 40
#: priorMDM's ``--handshake_size`` default (frames DoubleTake's first take blends)
DOUBLETAKE_HANDSHAKE = 20


def _doubletake_class() -> type:
    """An MDM whose class name says DoubleTake (priorMDM's ``doubleTake_MDM`` is recognised so)."""
    from ..reference.backbone import TinyMDM

    return type("DoubleTakeTinyMDM", (TinyMDM,), {"__doc__": "TinyMDM as priorMDM's doubleTake_MDM."})


class MDMWorkload(Workload):
    """``TinyMDM`` at MDM's HumanML3D size (latent 512, 8 layers, 4 heads, ff 1024), ``trans_enc`` /
    ``trans_dec`` (by default), ``dip`` (DiP: trans_dec with the step embedding as a token,
    :data:`DIP_CONTEXT` prefix frames given, :data:`DIP_PRED` frames predicted: ``frames`` does
    not apply) and ``doubletake`` (priorMDM's model, trans_enc; sampling calls carry the first
    take's handshake frames, ``is_transition``, as forced keyframes); normal features
    ``[B, 263, 1, N]``, cached text embeddings; sampling with classifier-free guidance (two passes
    per step) as MDM samples."""

    family, fsq, passes = "mdm", True, 2
    archs = ("trans_enc", "trans_dec", "dip", "doubletake")
    default_archs = ("trans_enc", "trans_dec")

    def size(self, quick: bool) -> Dict[str, int]:
        if quick:
            return dict(latent_dim=64, ff_size=128, num_layers=2, num_heads=4)
        return dict(latent_dim=512, ff_size=1024, num_layers=8, num_heads=4)

    def model(self, arch: str, quick: bool, frames: int, root: Optional[str] = None) -> torch.nn.Module:
        from ..reference.backbone import TinyMDM

        if arch == "dip":
            return TinyMDM(arch="trans_dec", emb_trans_dec=True, context_len=DIP_CONTEXT, pred_len=DIP_PRED,
                           **self.size(quick))
        if arch == "doubletake":
            return _doubletake_class()(arch="trans_enc", **self.size(quick))
        return TinyMDM(arch=arch, **self.size(quick))

    def model_family(self, arch: str) -> str:
        return "doubletake" if arch == "doubletake" else self.family

    def source(self, root: Optional[str]) -> str:
        return "in-package TinyMDM"

    def batch(self, batch: int, frames: int, device: torch.device, quick: bool,
              arch: Optional[str] = None, seed: int = 0) -> WorkloadBatch:
        from ..families.mdm.model import frames_layout

        g = torch.Generator().manual_seed(seed)
        frames = DIP_PRED if arch == "dip" else frames
        lengths = torch.full((batch,), frames) if arch == "dip" else valid_lengths(batch, frames, 40, g)
        valid = torch.arange(frames) < lengths[:, None]
        x = (torch.randn(batch, 263, 1, frames, generator=g) * valid.view(batch, 1, 1, frames)).to(device)
        y = {"mask": valid.view(batch, 1, 1, frames).to(device), "lengths": lengths.to(device),
             "text_embed": torch.randn(1, batch, 512, generator=g).to(device)}
        if arch == "dip":
            y["prefix"] = torch.randn(batch, 263, 1, DIP_CONTEXT, generator=g).to(device)
        sampling = {}
        if arch == "doubletake":
            sampling["is_transition"] = handshake_frames(lengths, frames, DOUBLETAKE_HANDSHAKE).to(device)
        return WorkloadBatch(x, frames_layout(x), lengths, {"y": y}, sampling)

    def kwargs(self, data: WorkloadBatch) -> Dict[str, Any]:
        return {"y": dict(data.kwargs["y"])}

    def sample_kwargs(self, data: WorkloadBatch) -> Dict[str, Any]:
        return {"y": {**data.kwargs["y"], **data.sampling}}

    def denoiser(self, model: torch.nn.Module) -> torch.nn.Module:
        from ..reference.simple_diffusion import ClassifierFreeGuidance

        return ClassifierFreeGuidance(model.eval(), scale=2.5)

    def call_args(self, data: WorkloadBatch, mask: torch.Tensor, capacity: int) -> Tuple[tuple, Dict[str, Any]]:
        from ..adapters.request import with_request

        return (data.x, None, with_request(data.kwargs["y"], mask=mask, capacity=capacity)), {}

    def lead(self, model: torch.nn.Module) -> int:
        return 1 if model.arch == "trans_enc" or getattr(model, "emb_trans_dec", False) else 0


class MotionDiffuseWorkload(Workload):
    """MotionDiffuse's denoiser layout (:class:`~smdm_plugin.reference.motiondiffuse_denoiser.MotionDiffuseDenoiser`,
    latent 512, 8 layers, 8 heads, FFN 1024) on ``[B, N, 263]``; precomputed text features
    (``xf_proj``, ``xf_out`` of 77 tokens) as MotionDiffuse computes them once per prompt; one
    model call per sampling step (MotionDiffuse samples without guidance). Its self-attention is
    linear: no FSQ keys, no attention backend (the sparse model runs its own blocks on the K slots)."""

    family, archs, default_archs, fsq, passes = "motiondiffuse", ("motiondiffuse",), ("motiondiffuse",), False, 1
    root_env = "SMDM_MOTIONDIFFUSE_ROOT"

    def size(self, quick: bool) -> Dict[str, int]:
        from ..reference.motiondiffuse_denoiser import motiondiffuse_size

        return motiondiffuse_size(quick)

    def check_root(self, root: str) -> None:
        upstream_motion_transformer(root)

    def model(self, arch: str, quick: bool, frames: int, root: Optional[str] = None) -> torch.nn.Module:
        from ..reference.motiondiffuse_denoiser import MotionDiffuseDenoiser

        cls = MotionDiffuseDenoiser if root is None else upstream_motion_transformer(root)
        return cls(input_feats=263, num_frames=max(196, frames), **self.size(quick))

    def source(self, root: Optional[str]) -> str:
        return ("in-package MotionDiffuseDenoiser (MotionDiffuse's interface)" if root is None
                else f"upstream MotionDiffuse {root}")

    def batch(self, batch: int, frames: int, device: torch.device, quick: bool,
              arch: Optional[str] = None, seed: int = 0) -> WorkloadBatch:
        size = self.size(quick)
        g = torch.Generator().manual_seed(seed)
        lengths = valid_lengths(batch, frames, 40, g)
        x = torch.randn(batch, frames, 263, generator=g) * (torch.arange(frames) < lengths[:, None])[..., None]
        kw = {"length": lengths.to(device),
              "xf_proj": torch.randn(batch, 4 * size["latent_dim"], generator=g).to(device),
              "xf_out": torch.randn(batch, 77, size["text_latent_dim"], generator=g).to(device)}
        x = x.to(device)
        return WorkloadBatch(x, x, lengths, kw)

    def call_args(self, data: WorkloadBatch, mask: torch.Tensor, capacity: int) -> Tuple[tuple, Dict[str, Any]]:
        from ..adapters.request import with_request

        return (data.x, None, data.kwargs["length"]), with_request({}, "model_kwargs", mask=mask, capacity=capacity)

    def backend(self, backend: str, device: torch.device, compile_mode: str) -> str:
        return "n/a (linear attention)"


def without_dropout(model: torch.nn.Module) -> torch.nn.Module:
    """``model`` with dropout, attention dropout and condition dropout off, in place: a training
    step then draws nothing from torch's random streams, so it gives the same loss on every device
    and path (checks against a reference). Returns ``model``."""
    for m in model.modules():
        if isinstance(m, torch.nn.Dropout):
            m.p = 0.0
        elif isinstance(getattr(m, "dropout", None), float):    # MultiheadAttention's, FSQ attention's
            m.dropout = 0.0
    if hasattr(model, "cond_mask_prob"):
        model.cond_mask_prob = 0.0
    return model


def handshake_frames(lengths: torch.Tensor, frames: int, handshake: int) -> torch.Tensor:
    """bool ``[B, N]``: DoubleTake's first-take ``is_transition`` for ``B`` segments of ``lengths``
    (one per prompt, in order): the first ``handshake`` frames of every segment after the first and
    the last ``handshake`` valid frames of every segment before the last."""
    B = lengths.shape[0]
    i = torch.arange(frames)[None]
    head = (i < handshake) & (torch.arange(B) > 0)[:, None]
    tail = (i >= lengths[:, None] - handshake) & (i < lengths[:, None]) & (torch.arange(B) < B - 1)[:, None]
    return head | tail


def upstream_motion_transformer(root: str) -> type:
    """MotionDiffuse's own ``MotionTransformer`` class from the checkout ``root`` (the folder
    holding ``text2motion/``). Raises ``ValueError`` naming ``root`` when it is not one or cannot be
    imported (MotionDiffuse needs ``openai-clip`` and CLIP's weights)."""
    import importlib

    t2m = os.path.join(os.path.abspath(root), "text2motion")
    if not os.path.isfile(os.path.join(t2m, "models", "transformer.py")):
        raise ValueError(f"--root: {root} is not a MotionDiffuse checkout (no text2motion/models/transformer.py)")
    if t2m not in sys.path:
        sys.path.insert(0, t2m)
    try:
        return importlib.import_module("models.transformer").MotionTransformer
    except Exception as e:  # noqa: BLE001 - any import failure is the checkout's, said in one line
        raise ValueError(f"--root: cannot import MotionDiffuse's models.transformer from {t2m}: "
                         f"{type(e).__name__}: {e}") from None


#: the benchmark's workload per model family name
WORKLOADS: Registry[Workload] = Registry("benchmark workload")
for _w in (MDMWorkload(), MotionDiffuseWorkload()):
    WORKLOADS.register(_w.family, _w)


def family_choices() -> List[str]:
    """The registered model families the benchmark can time (those with a :class:`Workload`)."""
    from ..adapters.families import FAMILIES

    return [n for n in FAMILIES.names() if n in WORKLOADS]


def build(arch: str, reduction: Optional[float], device: torch.device, quick: bool, steps: int,
          backend: str = "auto", seed: int = 0, fsq: str = "paper", family: str = "mdm", frames: int = 196,
          root: Optional[str] = None, **sparse: Any) -> Tuple[torch.nn.Module, Any]:
    """(model, diffusion) of ``family``'s workload — dense when ``reduction`` is None. ``fsq``
    (:data:`FSQ_CHOICES`): which side gets FSQ-quantised attention keys (families whose attention
    has softmax keys). ``root``: an upstream checkout whose model class to use; ``sparse``: more
    :class:`~smdm_plugin.core.config.SparseConfig` fields."""
    from ..adapters.surgery import sparsify
    from ..core.config import SparseConfig
    from ..core.fsq import quantize_attention_keys
    from ..reference.simple_diffusion import SimpleDiffusion

    work = WORKLOADS.get(family)
    fsq = fsq if work.fsq else "off"
    torch.manual_seed(seed)
    model = work.model(arch, quick, frames, root).to(device)
    diffusion = SimpleDiffusion(steps)
    if reduction is not None:
        sparsify(model, SparseConfig(reduction=reduction, attention_backend=backend, fsq=fsq != "off", **sparse),
                 diffusion=diffusion, family=work.model_family(arch))
    elif fsq == "both":
        quantize_attention_keys(model, SparseConfig().fsq_levels)
    return model, diffusion
