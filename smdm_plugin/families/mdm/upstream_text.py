"""MDM/DiP text conditioning: the sMDM-stella text-encoder swap and an opt-in text-embedding cache.

Both are applied by :func:`apply_text_options`, which :func:`smdm_plugin.families.mdm.upstream.sparsify_mdm`
calls right after upstream's ``create_model_and_diffusion`` builds the model, for dense and sparse
runs alike. The patch (``patches/mdm.patch``) and the launcher (``smdm run``) both already call
``sparsify_mdm`` there, so neither needs anything more; :func:`install_hooks` has nothing to add.

* ``--sparse_text_encoder ID_OR_PATH`` (``SparseConfig.text_encoder``): MDM's CLIP (DiP's
  DistilBERT) is replaced by that frozen ``transformers`` encoder, pooled
  (:mod:`smdm_plugin.adapters.text_encoder`); ``embed_text`` takes its width. The option is in
  MDM's ``model`` argument group, so ``args.json`` keeps it and ``sample.generate`` /
  ``sample.edit`` / ``eval.eval_humanml`` rebuild the same encoder from the checkpoint with no
  flag. Environment: ``SMDM_TRUST_REMOTE_CODE=1`` lets ``transformers`` run modelling code shipped
  with the encoder (stella_en_1.5B_v5 ships its own); ``SMDM_TEXT_ENCODER_DTYPE`` (``float32`` |
  ``bfloat16`` | ``float16``) is the dtype of the encoder's weights.
* ``SMDM_TEXT_CACHE`` (environment; off when unset, empty, ``0`` or ``off``): cache each caption's
  embedding (:mod:`smdm_plugin.adapters.text_cache`). ``on`` / ``1`` / ``true``: 131,072 captions;
  an integer ``N >= 2``: ``N`` captions. It changes no result (the cached embedding is the one the
  encoder gives), only how often the encoder runs; it stays out of ``args.json``.
"""
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
