"""priorMDM (DoubleTake) integration: ``--sparse*`` options, sparsify where the model is built,
forced keyframes for DoubleTake's two takes."""
from __future__ import annotations

import functools
import os
import warnings
from typing import Any, Optional

from ...core.config import SparseConfig
from ...integrations._hooks import wrap_once
from ..mdm.upstream import _is_training, apply_compile, dataset_mean_std, patch_base_options, patch_model_options
from ...integrations.options import add_sparse_options  # noqa: F401  (0.7.0's patches import it here; patches/priormdm.patch: .options)
from ...integrations.checkouts import Integration


def warn_if_not_paper_blend(args: Any) -> bool:
    """Warn (never override) when a sparse DoubleTake samples with a ``--blend_len`` other than the
    paper's 0.25 s (5 frames at 20 fps); priorMDM's own default is 20. Returns whether it warned."""
    from .model import PAPER_BLEND_LEN, PRIORMDM_BLEND_LEN

    blend = getattr(args, "blend_len", None)
    if blend is None or int(blend) == PAPER_BLEND_LEN:
        return False
    default = " (priorMDM's default)" if int(blend) == PRIORMDM_BLEND_LEN else ""
    warnings.warn(f"smdm: DoubleTake --blend_len {int(blend)}{default}; the sMDM paper blends transitions "
                  f"over 0.25 s = {PAPER_BLEND_LEN} frames at 20 fps. Pass --blend_len {PAPER_BLEND_LEN} to "
                  "follow it; this run is left unchanged.", stacklevel=3)
    return True


def _forced_bound(args: Any) -> Optional[int]:
    """:func:`~.model.doubletake_forced_bound` of the run's ``--handshake_size`` and ``--blend_len``
    (priorMDM's sampling options), or None when the run has not both (each call then reads its
    forced frames)."""
    from .model import doubletake_forced_bound

    h, b = getattr(args, "handshake_size", None), getattr(args, "blend_len", None)
    if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in (h, b)):
        return None
    return doubletake_forced_bound(h, b)


def sparsify_priormdm(model: Any, args: Any, data: Any = None, diffusion: Any = None,
                      config: Optional[SparseConfig] = None) -> Any:
    """Sparsify a priorMDM model built by ``create_model_and_diffusion`` (no-op unless
    ``args.sparse``); DoubleTake models also get their forced keyframes (see
    :mod:`smdm_plugin.families.doubletake.model`) and a warning when ``--blend_len`` is not the paper's.
    Training (``--save_dir``) writes ``sparse_config.json`` beside the weights and brings
    ``args.json``'s ``sparse_*`` entries to what ran; DoubleTake sampling writes it beside its
    ``results.npy``. Returns the model (changed in place)."""
    from .model import attach_doubletake_forcing
    from ...adapters.surgery import is_sparse
    from ...integrations._rng import upstream_rng_untouched
    from ...integrations.start import apply as apply_start, record_origin, resolve

    config = config if config is not None else SparseConfig.from_args(args)
    if not (config.enabled or getattr(args, "sparse_preset", None)):
        from ...integrations.options import refuse_dropped_sparse_options

        refuse_dropped_sparse_options(args)            # --sparse_* settings without --sparse: never dropped silently
        return model
    from ...integrations.messages import show_plugin_warnings

    show_plugin_warnings()
    start = resolve(args, config, _is_training(args))   # --sparse_preset / --sparse_init_from (start.py)
    config = start.config
    if not config.enabled or is_sparse(model):
        return model
    mean, std = dataset_mean_std(data)
    if mean is None and config.feature != "raw":
        warnings.warn("smdm: no dataset Mean/Std found on the data loader; keyframes are selected "
                      "on normalised features")
    with upstream_rng_untouched():  # a sparse DoubleTake draws the same prompts / noise as a dense one
        apply_start(model, args, start, diffusion, mean, std, data)   # sparsify, or wrap / warm start
    from ..mdm.model import is_doubletake_model   # here: `smdm run` imports this module without torch

    doubletake = is_doubletake_model(model)
    from ...integrations.announce import announce_sparse_mode

    training = _is_training(args)
    announce_sparse_mode(model, "priorMDM DoubleTake" if doubletake else "priorMDM", training)
    if doubletake:
        attach_doubletake_forcing(model, forced_bound=_forced_bound(args))
        warn_if_not_paper_blend(args)
    save_dir = getattr(args, "save_dir", None)
    if training and os.path.isdir(save_dir):  # sparse_config.json; args.json as resolved
        from ...integrations._files import record_run_config

        record_run_config(model, save_dir, args, os.path.join(save_dir, "args.json"),
                          overwrite=bool(getattr(args, "overwrite", False)))
        record_origin(args, os.path.join(save_dir, "args.json"))
    elif doubletake and getattr(args, "model_path", None):   # beside results.npy, when the process ends
        from ...integrations._files import record_sampling_output

        record_sampling_output(model, doubletake_output_dir(args))
    return model


def doubletake_output_dir(args: Any) -> Optional[str]:
    """The folder priorMDM's ``sample/double_take.py`` writes its ``results.npy`` to, derived from
    its parsed options exactly as it derives it: ``--output_dir`` when given, else beside
    ``--model_path``: ``DoubleTake_samples_<model folder>_<checkpoint number>_seed<seed>``, then
    ``_<text file name>`` (``--input_text`` .txt/.csv: extension, spaces and dots dropped), ``_gt``
    (``--sample_gt``), ``_handshake_<handshake_size>`` and, with ``--double_take``,
    ``_double_take_blend_<blend_len>_skipSteps_<skip_steps_double_take>``. Absolute (resolved
    against the current folder, as upstream's relative one is). None when upstream would not run
    (an ``--input_text`` that is neither .txt nor .csv) or ``--model_path`` is missing."""
    out = getattr(args, "output_dir", "") or ""
    if out:
        return os.path.abspath(out)
    model_path = getattr(args, "model_path", None)
    if not model_path:
        return None
    name = os.path.basename(os.path.dirname(model_path))
    niter = os.path.basename(model_path).replace("model", "").replace(".pt", "")
    out = os.path.join(os.path.dirname(model_path), f"DoubleTake_samples_{name}_{niter}_seed{getattr(args, 'seed', 10)}")
    text = getattr(args, "input_text", "") or ""
    if text:
        ext = ".txt" if ".txt" in text else ".csv" if ".csv" in text else None
        if ext is None:
            return None
        out += "_" + os.path.basename(text).replace(ext, "").replace(" ", "_").replace(".", "")
    if getattr(args, "sample_gt", False):
        out += "_gt"
    out += f"_handshake_{getattr(args, 'handshake_size', 20)}"
    if getattr(args, "double_take", False):
        out += f"_double_take_blend_{args.blend_len}_skipSteps_{args.skip_steps_double_take}"
    return os.path.abspath(out)


# --------------------------------------------------------------------------- import hooks
def _patch_model_util(mod) -> None:
    def make(original):
        @functools.wraps(original)
        def create_model_and_diffusion(args, data, *a, **kw):
            model, diffusion = original(args, data, *a, **kw)
            if getattr(args, "sparse", False) or getattr(args, "sparse_preset", None):
                sparsify_priormdm(model, args, data, diffusion)
            apply_compile(model, args, diffusion=diffusion)  # --sparse_compile (none: nothing)
            return model, diffusion
        return create_model_and_diffusion

    wrap_once(mod, "create_model_and_diffusion", make)


def install_hooks() -> None:
    """Wrap priorMDM's ``utils.parser_util.add_model_options``,
    ``utils.model_util.create_model_and_diffusion`` and ``model.cfg_sampler.ClassifierFreeSampleModel``
    as they are imported (idempotent; a checkout
    that already carries ``patches/priormdm.patch`` is not sparsified twice)."""
    from ...integrations._hooks import on_import
    from ...integrations.messages import show_plugin_warnings
    from ..mdm.upstream_guidance import install_hooks as install_guidance_hooks

    show_plugin_warnings()
    on_import("utils.parser_util", patch_model_options)
    on_import("utils.parser_util", patch_base_options)
    on_import("utils.model_util", _patch_model_util)
    install_guidance_hooks("model.cfg_sampler")     # --sparse_compile: both guidance passes, one graph


def is_priormdm_repo(path: str) -> bool:
    """A priorMDM checkout: MDM's layout plus ``model/DoubleTake_MDM.py``."""
    return os.path.isfile(os.path.join(path, "model", "DoubleTake_MDM.py"))


#: the upstream checkout `smdm run` hooks (this family's FamilySpec names it)
INTEGRATION = Integration(
    "priormdm", detect=is_priormdm_repo, install_hooks=install_hooks, priority=10,
    layout="model/DoubleTake_MDM.py (priorMDM)")
