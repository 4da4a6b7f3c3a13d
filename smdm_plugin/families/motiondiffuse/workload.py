"""What ``smdm bench --family motiondiffuse`` times: MotionDiffuse's denoiser layout (the
in-package :class:`~smdm_plugin.reference.motiondiffuse_denoiser.MotionDiffuseDenoiser`), or
MotionDiffuse's own class from a checkout (``--root``)."""
from __future__ import annotations

import os
import sys
from typing import Any, Dict, Optional, Tuple

import torch

from ...training.workloads import Workload, WorkloadBatch, valid_lengths


class MotionDiffuseWorkload(Workload):
    """MotionDiffuse's denoiser layout (:class:`~smdm_plugin.reference.motiondiffuse_denoiser.MotionDiffuseDenoiser`,
    latent 512, 8 layers, 8 heads, FFN 1024) on ``[B, N, 263]``; precomputed text features
    (``xf_proj``, ``xf_out`` of 77 tokens) as MotionDiffuse computes them once per prompt; one
    model call per sampling step (MotionDiffuse samples without guidance). Its self-attention is
    linear: no FSQ keys, no attention backend (the sparse model runs its own blocks on the K slots)."""

    family, archs, default_archs, fsq, passes = "motiondiffuse", ("motiondiffuse",), ("motiondiffuse",), False, 1
    root_env = "SMDM_MOTIONDIFFUSE_ROOT"

    def size(self, quick: bool) -> Dict[str, int]:
        from ...reference.motiondiffuse_denoiser import motiondiffuse_size

        return motiondiffuse_size(quick)

    def check_root(self, root: str) -> None:
        upstream_motion_transformer(root)

    def model(self, arch: str, quick: bool, frames: int, root: Optional[str] = None) -> torch.nn.Module:
        from ...reference.motiondiffuse_denoiser import MotionDiffuseDenoiser

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
        from ...adapters.request import with_request

        return (data.x, None, data.kwargs["length"]), with_request({}, "model_kwargs", mask=mask, capacity=capacity)

    def backend(self, backend: str, device: torch.device, compile_mode: str) -> str:
        return "n/a (linear attention)"


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
