"""What ``smdm bench --family mdm`` times: TinyMDM at MDM's HumanML3D size (``trans_enc`` /
``trans_dec``; on request DiP's prefix completion ``dip`` and priorMDM's DoubleTake model
``doubletake``)."""
from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import torch

from ...training.workloads import Workload, WorkloadBatch, handshake_frames, valid_lengths


#: DiP's windows (its defaults at 20 fps): ``context_len`` prefix frames, then ``pred_len`` frames
DIP_CONTEXT, DIP_PRED = 20, 40
#: priorMDM's ``--handshake_size`` default (frames DoubleTake's first take blends)
DOUBLETAKE_HANDSHAKE = 20


def _doubletake_class() -> type:
    """An MDM whose class name says DoubleTake (priorMDM's ``doubleTake_MDM`` is recognised so)."""
    from ...reference.backbone import TinyMDM

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
        from ...reference.backbone import TinyMDM

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

    def sparsified(self, model: torch.nn.Module, arch: str) -> None:
        """DoubleTake: the bound on its forced frames that the priorMDM integration passes (its
        calls here are first takes: two handshakes per segment), so its sampling calls read nothing
        on the host."""
        if arch == "doubletake":
            from ..doubletake.model import attach_doubletake_forcing, doubletake_forced_bound

            attach_doubletake_forcing(model, forced_bound=doubletake_forced_bound(DOUBLETAKE_HANDSHAKE, 0))

    def batch(self, batch: int, frames: int, device: torch.device, quick: bool,
              arch: Optional[str] = None, seed: int = 0) -> WorkloadBatch:
        from .model import frames_layout

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
        from ...reference.simple_diffusion import ClassifierFreeGuidance

        return ClassifierFreeGuidance(model.eval(), scale=2.5)

    def call_args(self, data: WorkloadBatch, mask: torch.Tensor, capacity: int) -> Tuple[tuple, Dict[str, Any]]:
        from ...adapters.request import with_request

        return (data.x, None, with_request(data.kwargs["y"], mask=mask, capacity=capacity)), {}

    def lead(self, model: torch.nn.Module) -> int:
        return 1 if model.arch == "trans_enc" or getattr(model, "emb_trans_dec", False) else 0


