"""``load_checkpoint`` for every model family: io reads and validates the files and calls back here
to make the model what the saved config describes (io knows no model family)."""
from __future__ import annotations

from typing import Any, Iterable, Optional, Tuple

import torch.nn as nn

from ..core.config import SparseConfig
from ..io import checkpoint as _io
from .surgery import is_sparse, sparsify
from .text_encoder import swap_text_encoder, swapped_text_encoder


def prepare_model(model: nn.Module, config: SparseConfig, **sparsify_kwargs: Any) -> nn.Module:
    """Make a freshly built ``model`` what ``config`` describes: the text encoder the weights were
    trained with (``config.text_encoder``), then sparse mode through the model's family."""
    if config.text_encoder and swapped_text_encoder(model) != config.text_encoder:
        swap_text_encoder(model, config.text_encoder)
    if config.enabled and not is_sparse(model):
        sparsify(model, config, **sparsify_kwargs)
    return model


_io.register_model_preparer(prepare_model)


def load_checkpoint(path: str, model: Optional[nn.Module] = None, map_location: Any = "cpu",
                    strict: bool = True, allow_differences: Iterable[str] = (),
                    **sparsify_kwargs: Any) -> Tuple[nn.Module, Optional[SparseConfig]]:
    """Load ``path`` (a ``.pt`` state dict) re-creating sparse mode from the saved config, for any
    registered model family. Arguments as :func:`smdm_plugin.io.checkpoint.load_checkpoint`;
    ``sparsify_kwargs`` (``mean``, ``std``, ``diffusion``) go to :func:`sparsify`."""
    return _io.load_checkpoint(path, model, map_location=map_location, strict=strict,
                               allow_differences=allow_differences, prepare=prepare_model, **sparsify_kwargs)
