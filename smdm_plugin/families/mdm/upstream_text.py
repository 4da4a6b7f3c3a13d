"""MDM/DiP text conditioning: the sMDM-stella text-encoder swap and an opt-in text-embedding cache."""
from __future__ import annotations

import os
from typing import Any, Optional

from ...core.config import SparseConfig

ENV_CACHE = "SMDM_TEXT_CACHE"
ENV_TRUST_REMOTE_CODE = "SMDM_TRUST_REMOTE_CODE"
ENV_DTYPE = "SMDM_TEXT_ENCODER_DTYPE"
_OFF = ("", "0", "off", "false", "no")
_ON = ("1", "on", "true", "yes")
_DTYPES = ("float32", "bfloat16", "float16")


def cache_capacity_from_env(environ: Optional[dict] = None) -> int:
    """Captions the text cache holds according to ``SMDM_TEXT_CACHE`` (0: off)."""
    raw = (os.environ if environ is None else environ).get(ENV_CACHE, "").strip().lower()
    if raw in _OFF:
        return 0
    if raw in _ON:
        from ...adapters.text_cache import DEFAULT_CAPACITY

        return DEFAULT_CAPACITY
    try:
        value = int(raw)
    except ValueError:
        value = -1
    if value < 2:
        raise ValueError(f"{ENV_CACHE}={raw!r}: expected off/0, on/1, or a number of captions >= 2")
    return value


def encoder_options_from_env(environ: Optional[dict] = None) -> dict:
    """``trust_remote_code`` and ``dtype`` for :class:`HFTextEncoder` from the environment."""
    import torch

    env = os.environ if environ is None else environ
    trust = env.get(ENV_TRUST_REMOTE_CODE, "").strip().lower()
    if trust not in _OFF + _ON:
        raise ValueError(f"{ENV_TRUST_REMOTE_CODE}={trust!r}: expected 0/1")
    dtype = env.get(ENV_DTYPE, "").strip().lower()
    if dtype and dtype not in _DTYPES:
        raise ValueError(f"{ENV_DTYPE}={dtype!r}: expected one of {_DTYPES}")
    return {"trust_remote_code": trust in _ON, "dtype": getattr(torch, dtype) if dtype else None}


def apply_text_options(model: Any, config: SparseConfig, environ: Optional[dict] = None) -> Any:
    """Swap the text encoder (``config.text_encoder``) and install the text cache
    (``SMDM_TEXT_CACHE``) on an MDM/DiP model; idempotent, a no-op when neither is asked for."""
    capacity = cache_capacity_from_env(environ)
    if config.text_encoder:
        from ...adapters.text_encoder import swap_text_encoder, swapped_text_encoder

        if swapped_text_encoder(model) != config.text_encoder:
            if not hasattr(model, "embed_text"):
                raise ValueError(f"--sparse_text_encoder {config.text_encoder}: the model has no text "
                                 "conditioning (cond_mode must include 'text')")
            swap_text_encoder(model, config.text_encoder, **encoder_options_from_env(environ))
    if capacity and hasattr(model, "encode_text"):
        from ...adapters.text_cache import install_text_cache

        install_text_cache(model, capacity=capacity)
    return model


def install_hooks() -> None:
    """Register this extension's import hooks (called by :func:`smdm_plugin.families.mdm.upstream.install_hooks`).

    None are needed: :func:`apply_text_options` runs inside ``sparsify_mdm``, which the MDM hooks
    (and the patch) already call where the model is built."""
