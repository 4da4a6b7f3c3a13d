"""The benchmark workloads: how ``smdm bench`` builds, feeds and calls the in-package model of each
registered model family (:data:`~smdm_plugin.adapters.families.FAMILIES`).

One :class:`Workload` per family, its ``FamilySpec.workload`` (``families/<name>/workload.py``:
``mdm`` — TinyMDM at MDM's HumanML3D size, ``trans_enc`` / ``trans_dec``, and on request DiP's
prefix completion ``dip`` and priorMDM's DoubleTake model ``doubletake``; ``motiondiffuse`` —
MotionDiffuse's denoiser layout, or MotionDiffuse's own class from a checkout); :data:`WORKLOADS`
is filled from the specs (``WORKLOADS.register("mymodel", MyWorkload())`` adds one without a
family spec). :func:`build` makes the dense or sparse model and its diffusion;
:meth:`Workload.batch` a HumanML3D-like batch (:class:`WorkloadBatch`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import torch

from ..core.registry import Registry

__all__ = ["WorkloadBatch", "Workload", "WORKLOADS", "FSQ_CHOICES", "family_choices", "build", "handshake_frames",
           "valid_lengths", "without_dropout"]

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

    def sparsified(self, model: torch.nn.Module, arch: str) -> None:
        """What the upstream integration does to variant ``arch`` once it is sparse (default:
        nothing)."""

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


_FROM_FAMILIES: Dict[str, Any] = {}   # family name -> the spec its workload came from


def _from_families() -> None:
    """Keep :data:`WORKLOADS` in step with the registered families' ``FamilySpec.workload``."""
    from ..adapters.families import family_part, family_specs

    specs = {s.name: s for s in family_specs() if s.workload is not None}
    for name, spec in list(_FROM_FAMILIES.items()):
        if specs.get(name) is not spec:              # unregistered or replaced
            del _FROM_FAMILIES[name]
            WORKLOADS.unregister(name)
    for name, spec in specs.items():
        if name not in _FROM_FAMILIES:
            _FROM_FAMILIES[name] = spec
            WORKLOADS.register(name, family_part(spec, "workload"), replace=True)


#: the benchmark's workload per model family name: each family's ``FamilySpec.workload``, and any
#: registered here
WORKLOADS: Registry[Workload] = Registry("benchmark workload", fill=_from_families)


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

    if not isinstance(fsq, str) or fsq not in FSQ_CHOICES:     # fsq=False would read as on
        raise ValueError(f"build: fsq must be one of {sorted(FSQ_CHOICES)} (SparseConfig's fsq: "
                         f"fsq='off'), got {fsq!r}")
    work = WORKLOADS.get(family)
    fsq = fsq if work.fsq else "off"
    torch.manual_seed(seed)
    model = work.model(arch, quick, frames, root).to(device)
    diffusion = SimpleDiffusion(steps)
    if reduction is not None:
        sparsify(model, SparseConfig(reduction=reduction, attention_backend=backend, fsq=fsq != "off", **sparse),
                 diffusion=diffusion, family=work.model_family(arch))
        work.sparsified(model, arch)
    elif fsq == "both":
        quantize_attention_keys(model, SparseConfig().fsq_levels)
    return model, diffusion
