"""The one ``load_checkpoint`` (every model family) and ``save_sparse_config``: io reads and checks
the files (:mod:`smdm_plugin.io.checkpoint_files`, which knows no model family); here a model becomes
what the saved config describes."""
from __future__ import annotations

import os
from typing import Any, Iterable, Optional, Tuple, Union

import torch.nn as nn

from ..core.config import SparseConfig
from ..io import checkpoint_files as _io
from .family import ModelFamily
from .state import find_sparse_model, sparse_config_of
from .surgery import is_sparse, set_mean_std, sparsify
from .text_encoder import swap_text_encoder, swapped_text_encoder


def save_sparse_config(model_or_config: Union[nn.Module, SparseConfig], directory: str,
                       overwrite: bool = False) -> str:
    """Write the config of a sparse model (or ``config``) as ``sparse_config.json`` into
    ``directory``; returns its path. Rules of :func:`smdm_plugin.io.checkpoint_files.write_sparse_config`
    (the same config again is fine, another one needs ``overwrite``)."""
    config = model_or_config if isinstance(model_or_config, SparseConfig) else sparse_config_of(model_or_config)
    if config is None:
        raise ValueError("save_sparse_config: the model is not sparse; sparsify it first")
    return _io.write_sparse_config(config, directory, overwrite=overwrite)


def prepare_model(model: nn.Module, config: SparseConfig, **sparsify_kwargs: Any) -> nn.Module:
    """Make a freshly built ``model`` what ``config`` describes: the text encoder the weights were
    trained with (``config.text_encoder``), then sparse mode through the model's family."""
    if config.text_encoder and swapped_text_encoder(model) != config.text_encoder:
        swap_text_encoder(model, config.text_encoder)
    if config.enabled and not is_sparse(model):
        sparsify(model, config, **sparsify_kwargs)
    return model


def load_checkpoint(path: str, model: Optional[nn.Module] = None, map_location: Any = "cpu",
                    strict: bool = True, allow_differences: Iterable[str] = (), *,
                    mean: Any = None, std: Any = None, diffusion: Any = None,
                    family: Union[str, ModelFamily, None] = None) -> Tuple[nn.Module, Optional[SparseConfig]]:
    """Load ``path`` (a ``.pt`` state dict) re-creating sparse mode from the saved config, for any
    registered model family.

    Args:
        path: checkpoint file; ``sparse_config.json`` or ``args.json`` beside it says whether it is sparse.
        model: the freshly built dense model to load into (sparsified here with the saved config),
            or a model already sparse, whose config must then equal the saved one (a ``ValueError``
            names the fields that differ). None: build the in-package ``TinyMDM`` from
            ``backbone.json`` beside the checkpoint.
        allow_differences: config fields an already-sparse ``model`` may set differently from the
            saved config on purpose (e.g. ``("gamma",)`` to sample with another schedule).
        mean, std: the ``[D]`` dataset statistics a sparse model selects keyframes with (given to
            :func:`sparsify`, or to :func:`set_mean_std` of an already-sparse ``model``; a dense
            checkpoint needs none).
        diffusion, family: given to :func:`sparsify` when the model is sparsified here (``diffusion``
            with an already-sparse ``model`` is an error: attach it with ``attach_diffusion``).
    Returns:
        ``(model, config)``; config is None for a dense checkpoint.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"load_checkpoint: path must be a file path, got {type(path).__name__}")
    if model is not None and not isinstance(model, nn.Module):
        raise TypeError(f"load_checkpoint: model must be a torch.nn.Module or None, got {type(model).__name__}")
    path, allowed = os.fspath(path), _io.allowed_differences(allow_differences)
    state, config, source = _io.read_checkpoint(path, map_location)
    if model is None:
        model = _io.build_backbone(path)
    if config is not None and config.enabled and _io.model_is_sparse(model):
        _io.check_config_matches(sparse_config_of(model), config, source or path, allowed)
        if diffusion is not None:
            raise ValueError("load_checkpoint: diffusion= is attached when the model is sparsified here, but the "
                             "model is already sparse: call attach_diffusion(diffusion, model)")
        if mean is not None or std is not None:
            set_mean_std(find_sparse_model(model), mean, std)
    if config is not None and (config.text_encoder or (config.enabled and not _io.model_is_sparse(model))):
        model = prepare_model(model, config, mean=mean, std=std, diffusion=diffusion, family=family)
    _io.load_weights(model, state, path, strict, source)
    return model, config
