"""Checkpoints: the sparse config lives beside the weights (``sparse_config.json``, and the
``sparse_*`` keys of MDM's ``args.json``); loading re-creates the sparse model, and loading a
sparse state dict into a dense model (or the reverse) is a clear error."""
from __future__ import annotations

import json
import os
from typing import Any, Dict, Mapping, Optional, Tuple, Union

import torch
import torch.nn as nn

from ..core.config import CONFIG_FILENAME, MARKER, SparseConfig

BACKBONE_FILENAME = "backbone.json"


def _dir_of(path: str) -> str:
    return path if os.path.isdir(path) else os.path.dirname(os.path.abspath(path))


def save_sparse_config(model_or_config: Union[nn.Module, SparseConfig], directory: str,
                       overwrite: bool = True) -> str:
    """Write ``sparse_config.json`` into ``directory``; returns its path."""
    config = model_or_config if isinstance(model_or_config, SparseConfig) else getattr(
        model_or_config, "smdm_config", None)
    if config is None:
        raise ValueError("save_sparse_config: the model is not sparse (no smdm_config); sparsify it first")
    os.makedirs(directory, exist_ok=True)
    path = os.path.join(directory, CONFIG_FILENAME)
    if os.path.exists(path) and not overwrite:
        raise FileExistsError(f"save_sparse_config: {path} exists (pass overwrite=True)")
    return config.save(path)


def find_sparse_config(checkpoint_path: str) -> Optional[SparseConfig]:
    """The config saved beside a checkpoint: ``sparse_config.json``, else ``args.json``'s
    ``sparse``/``sparse_*`` keys (MDM), else None."""
    d = _dir_of(checkpoint_path)
    p = os.path.join(d, CONFIG_FILENAME)
    if os.path.exists(p):
        return SparseConfig.load(p)
    args = os.path.join(d, "args.json")
    if os.path.exists(args):
        with open(args) as f:
            a = json.load(f)
        if a.get("sparse"):
            return SparseConfig.from_args(a)
    return None


def state_dict_is_sparse(state_dict: Mapping[str, Any]) -> bool:
    """Whether ``state_dict`` comes from a sparsified model (it carries the marker buffer)."""
    return any(k == MARKER or k.endswith("." + MARKER) for k in state_dict)


def model_is_sparse(model: nn.Module) -> bool:
    """Whether ``model`` (or a submodule) carries the sparse marker buffer (any adapter)."""
    return state_dict_is_sparse(dict(model.named_buffers()))


def check_state_dict(model: nn.Module, state_dict: Mapping[str, Any], source: str = "checkpoint") -> None:
    """Raise a clear error when a sparse state dict meets a dense model or the reverse."""
    sd_sparse = state_dict_is_sparse(state_dict)
    model_sparse = model_is_sparse(model)
    if sd_sparse and not model_sparse:
        raise RuntimeError(
            f"{source} holds a SPARSE (sMDM) model but the model being loaded is dense. Re-create it "
            "sparse: keep args.json/sparse_config.json beside the weights and use the patched "
            "upstream (or `smdm run`), pass --sparse, or call smdm_plugin.load_checkpoint().")
    if model_sparse and not sd_sparse:
        raise RuntimeError(f"{source} holds a DENSE model but the model is sparse; load it into a dense "
                           "model (drop --sparse) or train a sparse one")


def unwrap_state_dict(obj: Any) -> Dict[str, torch.Tensor]:
    """A model state dict from what ``torch.load`` returned (MDM: raw dict or ``{'model': ...}``)."""
    if isinstance(obj, Mapping) and "model" in obj and isinstance(obj["model"], Mapping):
        return dict(obj["model"])
    if isinstance(obj, Mapping) and "state_dict" in obj:
        return dict(obj["state_dict"])
    return dict(obj)


def load_checkpoint(path: str, model: Optional[nn.Module] = None, map_location: Any = "cpu",
                    strict: bool = True, **sparsify_kwargs: Any) -> Tuple[nn.Module, Optional[SparseConfig]]:
    """Load ``path`` (a ``.pt`` state dict) re-creating sparse mode from the saved config.

    Args:
        path: checkpoint file; ``sparse_config.json`` or ``args.json`` beside it says whether it is sparse.
        model: the freshly built dense model to load into. None: build the in-package ``TinyMDM``
            from ``backbone.json`` beside the checkpoint.
        sparsify_kwargs: passed to :func:`sparsify` (``mean``, ``std``, ``diffusion``).
    Returns:
        ``(model, config)``; config is None for a dense checkpoint.
    """
    from ..adapters.mdm import sparsify

    state = unwrap_state_dict(torch.load(path, map_location=map_location, weights_only=True))
    config = find_sparse_config(path)
    if state_dict_is_sparse(state) and config is None:
        raise RuntimeError(f"load_checkpoint: {path} holds a sparse model but has no sparse config beside it "
                           f"(expected {CONFIG_FILENAME} or args.json with sparse=true in "
                           f"{_dir_of(path)})")
    if model is None:
        bpath = os.path.join(_dir_of(path), BACKBONE_FILENAME)
        if not os.path.exists(bpath):
            raise FileNotFoundError(f"load_checkpoint: no model given and no {BACKBONE_FILENAME} beside "
                                    f"{path} to build the in-package TinyMDM")
        from ..reference.backbone import TinyMDM

        with open(bpath) as f:
            model = TinyMDM(**json.load(f))
    if config is not None and config.enabled and not model_is_sparse(model):
        sparsify(model, config, **sparsify_kwargs)
    check_state_dict(model, state, path)
    missing, unexpected = model.load_state_dict(state, strict=False)
    missing = [k for k in missing if not k.startswith("clip_model.")]
    if strict and (missing or unexpected):
        raise RuntimeError(f"load_checkpoint: {path} does not match the model: missing {missing[:5]}, "
                           f"unexpected {unexpected[:5]}")
    return model, config
