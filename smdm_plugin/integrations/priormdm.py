"""priorMDM (DoubleTake) integration: ``--sparse*`` options, sparsify where the model is built,
forced keyframes for DoubleTake's two takes.

Two ways in, same code path:

* ``patches/priormdm.patch`` (``git apply`` in a priorMDM checkout) calls
  :func:`add_sparse_options` from ``utils/parser_util.py:add_model_options`` and
  :func:`sparsify_priormdm` from ``utils/model_util.py:create_model_and_diffusion``;
* ``smdm run --repo PATH -- python -m sample.double_take ...`` calls :func:`install_hooks`,
  which wraps the same two functions when their modules are imported.

The options join priorMDM's ``model`` argument group, so ``train_mdm.py`` writes them to
``args.json`` and ``sample/double_take.py`` / ``eval/eval_humanml_double_take.py`` read them back
from there (``load_from_model`` overwrites the ``model`` group from the checkpoint's args).
"""
from __future__ import annotations

import functools
import warnings
from typing import Any, Optional

from ..core.config import SparseConfig


from .mdm import add_sparse_options  # noqa: E402,F401  (the one --sparse* adder; patches import it here)


def _dataset_mean_std(data: Any):
    """Mean/Std the loader normalises with (HumanML3D: ``dataset/HumanML3D/Mean.npy``)."""
    ds = getattr(data, "dataset", None)
    for obj in (ds, getattr(ds, "t2m_dataset", None)):
        mean, std = getattr(obj, "mean", None), getattr(obj, "std", None)
        if mean is not None and std is not None:
            return mean, std
    return None, None


def warn_if_not_paper_blend(args: Any) -> bool:
    """Warn (never override) when a sparse DoubleTake samples with a ``--blend_len`` other than the
    paper's 0.25 s (5 frames at 20 fps); priorMDM's own default is 20. Returns whether it warned."""
    from ..adapters.doubletake import PAPER_BLEND_LEN, PRIORMDM_BLEND_LEN

    blend = getattr(args, "blend_len", None)
    if blend is None or int(blend) == PAPER_BLEND_LEN:
        return False
    default = " (priorMDM's default)" if int(blend) == PRIORMDM_BLEND_LEN else ""
    warnings.warn(f"smdm: DoubleTake --blend_len {int(blend)}{default}; the sMDM paper blends transitions "
                  f"over 0.25 s = {PAPER_BLEND_LEN} frames at 20 fps. Pass --blend_len {PAPER_BLEND_LEN} to "
                  "follow it; this run is left unchanged.", stacklevel=3)
    return True


def sparsify_priormdm(model: Any, args: Any, data: Any = None, diffusion: Any = None,
                      config: Optional[SparseConfig] = None) -> Any:
    """Sparsify a priorMDM model built by ``create_model_and_diffusion`` (no-op unless
    ``args.sparse``); DoubleTake models also get their forced keyframes (see
    :mod:`smdm_plugin.adapters.doubletake`) and a warning when ``--blend_len`` is not the paper's.
    Returns the model (changed in place)."""
    from ..adapters.doubletake import attach_doubletake_forcing
    from ..adapters.surgery import is_sparse, sparsify
    from ._rng import upstream_rng_untouched

    config = config if config is not None else SparseConfig.from_args(args)
    if not config.enabled or is_sparse(model):
        return model
    mean, std = _dataset_mean_std(data)
    if mean is None and config.feature != "raw":
        warnings.warn("smdm: no dataset Mean/Std found on the data loader; keyframes are selected "
                      "on normalised features")
    with upstream_rng_untouched():  # a sparse DoubleTake draws the same prompts / noise as a dense one
        sparsify(model, config, diffusion=diffusion, mean=mean, std=std)
    if "doubletake" in type(model).__name__.lower():
        attach_doubletake_forcing(model)
        warn_if_not_paper_blend(args)
    return model


# --------------------------------------------------------------------------- import hooks
def _patch_parser_util(mod) -> None:
    original = getattr(mod, "add_model_options", None)
    if original is None or getattr(original, "_smdm_wrapped", False):
        return

    @functools.wraps(original)
    def add_model_options(parser):
        original(parser)
        for group in parser._action_groups:
            if group.title == "model":
                add_sparse_options(group)
                break

    add_model_options._smdm_wrapped = True
    mod.add_model_options = add_model_options


def _patch_model_util(mod) -> None:
    original = getattr(mod, "create_model_and_diffusion", None)
    if original is None or getattr(original, "_smdm_wrapped", False):
        return

    @functools.wraps(original)
    def create_model_and_diffusion(args, data, *a, **kw):
        model, diffusion = original(args, data, *a, **kw)
        if getattr(args, "sparse", False):
            sparsify_priormdm(model, args, data, diffusion)
        return model, diffusion

    create_model_and_diffusion._smdm_wrapped = True
    mod.create_model_and_diffusion = create_model_and_diffusion


def install_hooks() -> None:
    """Wrap priorMDM's ``utils.parser_util.add_model_options`` and
    ``utils.model_util.create_model_and_diffusion`` as they are imported (idempotent; a checkout
    that already carries ``patches/priormdm.patch`` is not sparsified twice)."""
    from ._hooks import on_import

    on_import("utils.parser_util", _patch_parser_util)
    on_import("utils.model_util", _patch_model_util)
