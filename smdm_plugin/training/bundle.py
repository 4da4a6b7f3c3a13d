"""A trained in-package model in one folder, ready to sample from (``smdm inbetween``, ``smdm demo``).

Layout of the folder::

    model.pt            the state dict (sparse models carry the sparse marker buffer); a folder of
                        ``smdm train`` holds model<step>.pt instead, and the last one is read
    backbone.json       TinyMDM's constructor arguments (read by load_checkpoint)
    sparse_config.json  sparse models only: the SparseConfig (read by load_checkpoint)
    motion.json         representation, feature mean / std, fps, frames, diffusion steps, notes
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from typing import Any, Dict, Optional

import numpy as np
import torch
import torch.nn as nn

from ..adapters.checkpoint import load_checkpoint, save_sparse_config
from ..adapters.state import sparse_config_of
from ..core.config import SparseConfig
from ..support.config_files import CONFIG_FILENAME
from ..io.checkpoint_files import BACKBONE_FILENAME, MOTION_FILENAME
from ..io.files import atomic_open, atomic_write_json
from ..io.representation import Representation
from ..io.validate import check_stats, float_field, int_field, read_json_object, require_fields
from ..reference.simple_diffusion import SimpleDiffusion

WEIGHTS_FILENAME = "model.pt"


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
    from ..io.outdir import OutputDir

    # written complete in a partial folder and swapped in: a reader sees the old model or the new one
    with OutputDir(directory, overwrite=overwrite, command="save_bundle", what="model folder",
                   owns=(WEIGHTS_FILENAME, BACKBONE_FILENAME, CONFIG_FILENAME, MOTION_FILENAME)) as od:
        part = od.path
        with atomic_open(os.path.join(part, WEIGHTS_FILENAME), "wb") as f:
            torch.save({k: v.detach().cpu() for k, v in model.state_dict().items()}, f)
        atomic_write_json(os.path.join(part, BACKBONE_FILENAME), dict(backbone))
        if sparse_config_of(model) is not None:
            save_sparse_config(model, part, overwrite=True)
        write_motion_meta(part, representation, mean, std, fps, max_frames, diffusion.num_timesteps, info)
    return directory


def write_motion_meta(directory: str, representation: Representation, mean: np.ndarray, std: np.ndarray,
                      fps: float, max_frames: int, diffusion_steps: int, info: Optional[Dict[str, Any]] = None) -> None:
    """Write ``motion.json`` (what :func:`load_bundle` needs besides the weights) into ``directory``;
    ``mean``/``std`` ``[D]`` of the representation's un-normalised features."""
    mean, std = np.asarray(mean, np.float64).reshape(-1), np.asarray(std, np.float64).reshape(-1)
    atomic_write_json(os.path.join(directory, MOTION_FILENAME), {
        "representation": representation.name, "mean": mean.tolist(), "std": std.tolist(), "fps": float(fps),
        "max_frames": int(max_frames), "diffusion_steps": int(diffusion_steps), "info": info or {}})


def weights_path(directory: str) -> str:
    """``model.pt`` (:func:`save_bundle`), else the last ``model<step>.pt`` (``smdm train``)."""
    path = os.path.join(directory, WEIGHTS_FILENAME)
    if os.path.exists(path):
        return path
    steps = sorted(n for n in os.listdir(directory) if re.fullmatch(r"model\d+\.pt", n))
    if not steps:
        raise FileNotFoundError(f"{directory!r}: no {WEIGHTS_FILENAME} or model<step>.pt")
    return os.path.join(directory, steps[-1])


def load_bundle(directory: str, device: Any = "cpu") -> ModelBundle:
    """Load a folder written by :func:`save_bundle` (model in ``eval`` mode on ``device``)."""
    meta_path = os.path.join(directory, MOTION_FILENAME)
    if not os.path.isdir(directory) or not os.path.exists(meta_path):
        raise FileNotFoundError(f"{directory!r} is not a model folder (no {MOTION_FILENAME}); train one with "
                                "`smdm demo --out DIR` (writes DIR/dense and DIR/sparse), `smdm train --out DIR` "
                                "or scripts/eval_inbetween.py")
    meta = read_json_object(meta_path)
    # every setting present (no defaults for a versioned file), typed and in range
    require_fields(meta, ("representation", "mean", "std", "fps", "max_frames", "diffusion_steps"), meta_path)
    try:
        rep = Representation(meta["representation"])
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{meta_path}: representation={meta['representation']!r}: {e}") from None
    steps = int_field(meta, "diffusion_steps", meta_path, lo=1)
    fps = float_field(meta, "fps", meta_path, lo=0.0)
    max_frames = int_field(meta, "max_frames", meta_path, lo=2)
    mean, std = check_stats(_array(meta["mean"], meta_path, "mean"), _array(meta["std"], meta_path, "std"),
                            rep.dim, meta_path)
    model, config = load_checkpoint(weights_path(directory), mean=mean, std=std)  # the run's files agreeing
    backbone = read_json_object(os.path.join(directory, BACKBONE_FILENAME))
    if backbone.get("njoints", rep.dim) * backbone.get("nfeats", 1) != rep.dim:
        raise ValueError(f"{os.path.join(directory, BACKBONE_FILENAME)}: njoints x nfeats="
                         f"{backbone.get('njoints')} x {backbone.get('nfeats', 1)} disagrees with {meta_path}'s "
                         f"representation {rep.name} ({rep.dim} features)")
    model.to(device).eval()
    return ModelBundle(model=model, diffusion=SimpleDiffusion(steps), representation=rep, mean=mean, std=std,
                       fps=fps, max_frames=max_frames,
                       config=config, path=directory, info=dict(meta.get("info", {})))


def _array(v: Any, where: str, name: str) -> np.ndarray:
    """A JSON list of numbers as an array (a ragged or non-numeric list names the file and field)."""
    try:
        arr = np.asarray(v)
    except ValueError:
        arr = None
    if arr is None or arr.dtype.kind not in "biuf":
        raise ValueError(f"{where}: {name} must be a list of numbers")
    return arr
