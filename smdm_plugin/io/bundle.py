"""A trained in-package model in one folder, ready to sample from (``smdm inbetween``, ``smdm demo``).

Layout of the folder::

    model.pt            the state dict (sparse models carry the sparse marker buffer)
    backbone.json       TinyMDM's constructor arguments (read by load_checkpoint)
    sparse_config.json  sparse models only: the SparseConfig (read by load_checkpoint)
    motion.json         representation, feature mean / std, fps, frames, diffusion steps, notes
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any, Dict, Optional

import numpy as np
import torch
import torch.nn as nn

from ..core.config import SparseConfig, sparse_config_of
from ..reference.diffusion import SimpleDiffusion
from .checkpoint import BACKBONE_FILENAME, load_checkpoint, save_sparse_config
from .files import atomic_open, atomic_write_json, check_new_dir
from .representation import Representation

WEIGHTS_FILENAME = "model.pt"
MOTION_FILENAME = "motion.json"


@dataclass
class ModelBundle:
    """A loaded model folder. ``mean``/``std`` ``[D]`` normalise the ``representation``'s features;
    ``fps`` frames per second; ``max_frames`` the longest motion it was trained on."""

    model: nn.Module
    diffusion: SimpleDiffusion
    representation: Representation
    mean: np.ndarray
    std: np.ndarray
    fps: float
    max_frames: int
    config: Optional[SparseConfig]
    path: str
    info: Dict[str, Any] = field(default_factory=dict)

    @property
    def sparse(self) -> bool:
        return self.config is not None and self.config.enabled

    @property
    def label(self) -> str:
        """``"sparse (80% dropped)"`` or ``"dense"``, for tables and figures."""
        return f"sparse ({round(self.config.reduction * 100)}% dropped)" if self.sparse else "dense"

    def normalise(self, features: torch.Tensor) -> torch.Tensor:
        return (features - torch.as_tensor(self.mean).to(features)) / torch.as_tensor(self.std).to(features)

    def denormalise(self, features: torch.Tensor) -> torch.Tensor:
        return features * torch.as_tensor(self.std).to(features) + torch.as_tensor(self.mean).to(features)


def save_bundle(directory: str, model: nn.Module, diffusion: SimpleDiffusion, backbone: Dict[str, Any],
                representation: Representation, mean: np.ndarray, std: np.ndarray, fps: float = 20.0,
                max_frames: int = 196, info: Optional[Dict[str, Any]] = None, overwrite: bool = False) -> str:
    """Write ``model`` (a ``TinyMDM`` built with ``backbone`` kwargs, dense or sparse) into
    ``directory`` (refused when it exists and is not empty, unless ``overwrite``); returns it."""
    mean, std = np.asarray(mean, np.float64).reshape(-1), np.asarray(std, np.float64).reshape(-1)
    if mean.shape != (representation.dim,) or std.shape != (representation.dim,):
        raise ValueError(f"save_bundle: mean and std must be [{representation.dim}] for {representation.name}, "
                         f"got {mean.shape}, {std.shape}")
    check_new_dir(directory, overwrite, what="model folder")
    with atomic_open(os.path.join(directory, WEIGHTS_FILENAME), "wb") as f:
        torch.save({k: v.detach().cpu() for k, v in model.state_dict().items()}, f)
    atomic_write_json(os.path.join(directory, BACKBONE_FILENAME), dict(backbone))
    config = sparse_config_of(model)
    stale = os.path.join(directory, "sparse_config.json")
    if config is not None:
        save_sparse_config(model, directory, overwrite=True)
    elif os.path.exists(stale):  # overwrite=True over a sparse bundle with a dense model
        os.unlink(stale)
    atomic_write_json(os.path.join(directory, MOTION_FILENAME), {
        "representation": representation.name, "mean": mean.tolist(), "std": std.tolist(), "fps": float(fps),
        "max_frames": int(max_frames), "diffusion_steps": int(diffusion.num_timesteps), "info": info or {}})
    return directory


def load_bundle(directory: str, device: Any = "cpu") -> ModelBundle:
    """Load a folder written by :func:`save_bundle` (model in ``eval`` mode on ``device``)."""
    meta_path = os.path.join(directory, MOTION_FILENAME)
    if not os.path.isdir(directory) or not os.path.exists(meta_path):
        raise FileNotFoundError(f"{directory!r} is not a model folder (no {MOTION_FILENAME}); train one with "
                                "`smdm demo --out DIR` (writes DIR/dense and DIR/sparse) or "
                                "scripts/eval_inbetween.py")
    try:
        with open(meta_path) as f:
            meta = json.load(f)
        rep = Representation(meta["representation"])
        mean, std = np.asarray(meta["mean"], np.float32), np.asarray(meta["std"], np.float32)
        steps = int(meta["diffusion_steps"])
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{meta_path}: not a valid {MOTION_FILENAME} ({e})") from None
    model, config = load_checkpoint(os.path.join(directory, WEIGHTS_FILENAME), mean=mean, std=std)
    model.to(device).eval()
    return ModelBundle(model=model, diffusion=SimpleDiffusion(steps), representation=rep, mean=mean, std=std,
                       fps=float(meta.get("fps", 20.0)), max_frames=int(meta.get("max_frames", 196)),
                       config=config, path=directory, info=dict(meta.get("info", {})))
