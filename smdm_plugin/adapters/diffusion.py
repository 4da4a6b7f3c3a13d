"""Wrap a Gaussian diffusion's ``training_losses`` (MDM / guided-diffusion style, or the
in-package :class:`~smdm_plugin.diffusion.SimpleDiffusion`) for sparse training:

* the keyframe mask is selected from the clean motion ``x_start`` (+ mask noise) and handed to
  the model as ``y['keyframe_mask']``;
* the loss stays on the dense, interpolated frames with the upstream valid-frame mask — or on
  keyframes only when ``config.interpolate`` is False (ablation);
* ``config.lipschitz_lambda * L_lip`` is added to ``terms['loss']``.
"""
from __future__ import annotations

import functools
from typing import Any, Optional

import torch
import torch.nn as nn

from ..core.config import SparseConfig
from ..core.losses import add_lipschitz_term
from .state import find_sparse_model, frames_layout, get_state, lengths_from_y


def diffusion_steps(diffusion: Any) -> int:
    """T of the training schedule (``original_num_steps`` of a respaced diffusion)."""
    for attr in ("original_num_steps", "num_timesteps", "num_steps", "T"):
        if getattr(diffusion, attr, None):
            return int(getattr(diffusion, attr))
    raise ValueError(f"attach_diffusion: cannot read the step count of {type(diffusion).__name__} "
                     "(expected num_timesteps or original_num_steps)")


def attach_diffusion(diffusion: Any, config: SparseConfig, model: Optional[nn.Module] = None) -> Any:
    """Wrap ``diffusion.training_losses`` in place (idempotent) and return ``diffusion``."""
    if getattr(diffusion, "_smdm_attached", False):
        return diffusion
    original = diffusion.training_losses

    @functools.wraps(original)
    def training_losses(model_arg, x_start, t, model_kwargs=None, *args, **kwargs):
        sparse = model if model is not None else find_sparse_model(model_arg)
        if sparse is None:  # a dense model given to a sparse diffusion: behave as upstream
            return original(model_arg, x_start, t, model_kwargs, *args, **kwargs)
        model_kwargs = dict(model_kwargs or {})
        y = dict(model_kwargs.get("y", {}))
        frames = frames_layout(x_start)
        B, N = frames.shape[:2]
        lengths = lengths_from_y(y, B, N, x_start.device)
        mask = get_state(sparse).schedule.training_mask(frames, lengths, y.get("keyframe_forced"))
        y["keyframe_mask"] = mask
        if not config.interpolate and isinstance(y.get("mask"), torch.Tensor):
            y["mask"] = y["mask"] & mask.view(y["mask"].shape).to(y["mask"].dtype)
        model_kwargs["y"] = y
        terms = original(model_arg, x_start, t, model_kwargs, *args, **kwargs)
        return add_lipschitz_term(terms, sparse, config, B)

    diffusion.training_losses = training_losses
    diffusion._smdm_attached = True
    diffusion._smdm_original_training_losses = original
    return diffusion


def detach_diffusion(diffusion: Any) -> Any:
    """Undo :func:`attach_diffusion`."""
    if getattr(diffusion, "_smdm_attached", False):
        del diffusion.training_losses
        del diffusion._smdm_attached
        del diffusion._smdm_original_training_losses
    return diffusion
