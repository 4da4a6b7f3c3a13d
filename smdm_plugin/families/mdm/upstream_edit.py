"""MDM's ``sample.edit`` with a sparse checkpoint: the frames the edit keeps become forced keyframes."""
from __future__ import annotations

import functools
import inspect
import os
from typing import Any, Dict, Optional

import torch

from ...integrations._hooks import wrap_once

ENV_POLICY = "SMDM_EDIT_FORCED"
DEFAULT_POLICY = "ends"


def _sparse_model(model: Any) -> Optional[Any]:
    """The sparsified module inside ``model`` (ClassifierFreeSampleModel, DDP, respacing wrappers)."""
    from ...adapters.state import find_sparse_model

    seen = set()
    while model is not None and id(model) not in seen:
        seen.add(id(model))
        if isinstance(model, torch.nn.Module):
            found = find_sparse_model(model)
            if found is not None:
                return found
        model = getattr(model, "model", None)
    return None


def policy_from_env() -> str:
    from ...adapters.inbetween_sampling import POLICIES

    policy = os.environ.get(ENV_POLICY, DEFAULT_POLICY).strip() or DEFAULT_POLICY
    if policy not in POLICIES:
        raise ValueError(f"{ENV_POLICY}={policy!r}: expected one of {POLICIES}")
    return policy


def forced_for_edit(model: Any, model_kwargs: Optional[Dict[str, Any]], policy: Optional[str] = None
                    ) -> Optional[Dict[str, Any]]:
    """``model_kwargs`` with forced keyframes added to ``y`` (``smdm_plugin.with_forced``) when
    ``model`` is sparse and ``y`` has MDM's in-painting keys (a new dict; the caller's is not
    changed), else ``model_kwargs`` itself."""
    from ...adapters.inbetween_sampling import forced_keyframes, frames_from_inpainting_mask
    from ...adapters.request import request_of, with_forced

    y = (model_kwargs or {}).get("y")
    if (not isinstance(y, dict) or "inpainting_mask" not in y or "inpainted_motion" not in y
            or _sparse_model(model) is None or request_of(y).forced is not None):
        return model_kwargs
    motion = y["inpainted_motion"]
    B, N = motion.shape[0], motion.shape[-1]
    frames = frames_from_inpainting_mask(y["inpainting_mask"], motion.shape)
    if y.get("lengths") is not None:
        lengths = torch.as_tensor(y["lengths"], device=frames.device)
    elif isinstance(y.get("mask"), torch.Tensor) and y["mask"].shape[-1] == N:
        lengths = y["mask"].reshape(B, N).to(frames.device).long().sum(1)
    else:
        lengths = None
    forced = forced_keyframes(frames, lengths, policy or policy_from_env())
    return {**model_kwargs, "y": with_forced(y, forced)}


def add_forced_keyframes(model: Any, model_kwargs: Dict[str, Any], policy: Optional[str] = None) -> None:
    """In place: ``model_kwargs['y']`` forces the kept frames of a sparse ``model`` (see
    :func:`forced_for_edit`); the one call patch users add to ``sample/edit.py``."""
    from ...adapters.request import KEYFRAMES_KEY

    new = forced_for_edit(model, model_kwargs, policy)
    if new is not model_kwargs:
        model_kwargs["y"][KEYFRAMES_KEY] = new["y"][KEYFRAMES_KEY]


def _patch_gaussian_diffusion(mod: Any) -> None:
    def make(original):
        signature = inspect.signature(original)

        @functools.wraps(original)
        def p_sample_loop(self, *args, **kwargs):
            bound = signature.bind(self, *args, **kwargs)
            kw = bound.arguments.get("model_kwargs")
            new = forced_for_edit(bound.arguments.get("model"), kw)
            if new is not kw:
                bound.arguments["model_kwargs"] = new
            return original(*bound.args, **bound.kwargs)
        return p_sample_loop

    wrap_once(getattr(mod, "GaussianDiffusion", None), "p_sample_loop", make)


def install_hooks() -> None:
    """Wrap MDM's ``GaussianDiffusion.p_sample_loop`` as ``diffusion.gaussian_diffusion`` is
    imported (idempotent; called by :func:`smdm_plugin.families.mdm.upstream.install_hooks`)."""
    from ...integrations._hooks import on_import

    on_import("diffusion.gaussian_diffusion", _patch_gaussian_diffusion)
