"""MDM (and DiP, which lives in the same repository) integration: ``--sparse*`` options,
sparsify where the model and diffusion are built, dense/sparse checkpoint checks."""
from __future__ import annotations

import argparse
import functools
import os
import warnings
from typing import Any, Optional, Tuple

from ...core.config import SparseConfig
from ...support.config_files import CONFIG_FILENAME
from ...integrations._hooks import wrap_once
from ...integrations.options import add_sparse_options  # noqa: F401  (0.7.0's patches import it here; patches/mdm.patch: .options)
from ...integrations.checkouts import Integration

__all__ = ["add_sparse_options", "apply_compile", "sparsify_mdm", "check_mdm_state_dict", "dataset_mean_std",
           "install_hooks", "is_mdm_repo", "patch_base_options", "patch_model_options", "sample_output_dir",
           "warn_if_upstream_steps"]


def is_mdm_repo(path: str) -> bool:
    """An MDM / DiP checkout (priorMDM shares the layout but has ``model/DoubleTake_MDM.py``)."""
    return (os.path.isfile(os.path.join(path, "model", "mdm.py"))
            and os.path.isfile(os.path.join(path, "utils", "model_util.py"))
            and not os.path.isfile(os.path.join(path, "model", "DoubleTake_MDM.py")))


def dataset_mean_std(data: Any) -> Tuple[Any, Any]:
    """The Mean/Std MDM's HumanML3D/KIT loader normalises with (``dataset/HumanML3D/Mean.npy``),
    from a DataLoader or a dataset; ``(None, None)`` when not reachable."""
    ds = getattr(data, "dataset", data)
    for obj in (ds, getattr(ds, "t2m_dataset", None)):
        mean, std = getattr(obj, "mean", None), getattr(obj, "std", None)
        if mean is not None and std is not None:
            return mean, std
    return None, None


def _is_training(args: Any) -> bool:
    """``train.train_mdm`` parses a ``save_dir``; sampling / editing / evaluation a ``model_path``."""
    return bool(getattr(args, "save_dir", None)) and not getattr(args, "model_path", None)


#: diffusion steps of upstream MDM's default schedule; sparse training there gets a warning
UPSTREAM_STEPS = 1000


def warn_if_upstream_steps(config: SparseConfig, steps: Optional[int]) -> bool:
    """Warn (never override) when sparse training runs at upstream's 1000 diffusion steps: the
    paper's sMDM is trained at 50 (App. B.1, Table 1) and its Table 2 compares step counts.
    Returns whether it warned."""
    if not config.enabled or steps is None or int(steps) != UPSTREAM_STEPS:
        return False
    warnings.warn(
        f"smdm: sparse training at {UPSTREAM_STEPS} diffusion steps (upstream MDM's default). The paper's "
        "sMDM is trained at 50 (App. B.1; Table 1's headline model), and its Table 2 (sMDM at fewer steps) "
        "shows the dynamic keyframe update helping at >= 100 steps and neutral to worse at 50 and 10. "
        "Pass --diffusion_steps 50 (preset smdm_paper) to follow the paper; this run is left unchanged.",
        stacklevel=3)
    return True


def sparsify_mdm(model: Any, args: Any, data: Any = None, diffusion: Any = None,
                 config: Optional[SparseConfig] = None) -> Any:
    """The plugin's entry point right after MDM's ``create_model_and_diffusion`` (patch and launcher).

    1. Text options, dense or sparse (:func:`.mdm_text.apply_text_options`): the sMDM-stella
       encoder swap (``--sparse_text_encoder``) and the opt-in text cache (``SMDM_TEXT_CACHE``);
       nothing when neither is asked for.
    2. When ``args.sparse`` (or ``--sparse_preset``): sparsify the MDM/DiP model, wrap
       ``diffusion.training_losses`` (keyframe masks from x0, ``lambda * L_lip``), say so in one
       line (:mod:`.announce`) and, when training (``args.save_dir``), write ``sparse_config.json``
       beside the weights, bring ``args.json``'s ``sparse_*`` entries to the settings that ran, and
       warn if the run uses upstream's 1000 diffusion steps; when sampling (``sample.generate`` /
       ``sample.edit``, DiP's too), write ``sparse_config.json`` beside ``results.npy`` at the end.
    3. ``--sparse_compile`` (dense or sparse): :func:`apply_compile`.

    Without ``--sparse``, ``--sparse_preset``, a text option or ``--sparse_compile`` the model is
    returned untouched, bit for bit, and nothing more of the plugin is imported. Otherwise the
    plugin's warnings are shown as ``smdm:`` lines whatever logging upstream set up
    (:mod:`smdm_plugin.integrations.messages`).
    """
    if config is None and not _asks_for_anything(args):
        from ...integrations.options import refuse_dropped_sparse_options   # (loaded already: it added the options)

        refuse_dropped_sparse_options(args)            # --sparse_* settings without --sparse: never dropped silently
        return model                                   # a flag-off run: upstream's model
    from ...integrations.messages import show_plugin_warnings

    show_plugin_warnings()
    from ...adapters.surgery import is_sparse
    from ...integrations._rng import upstream_rng_untouched
    from .upstream_text import apply_text_options

    config = config if config is not None else SparseConfig.from_args(args)
    with upstream_rng_untouched():  # a swapped text encoder's new layers draw from a forked stream
        apply_text_options(model, config)
    from ...integrations.start import resolve

    start = resolve(args, config, _is_training(args))   # --sparse_preset / --sparse_init_from (start.py)
    config = start.config
    if config.enabled and not is_sparse(model):  # sparse already: patch + launcher together
        _sparsify(model, args, data, diffusion, config, start)
    apply_compile(model, args, diffusion=diffusion)
    return model


def _asks_for_anything(args: Any) -> bool:
    """Whether the run asks the plugin for anything: ``--sparse``, ``--sparse_preset``,
    ``--sparse_init_from``, ``--sparse_text_encoder``, the text cache (``SMDM_TEXT_CACHE``) or
    ``--sparse_compile`` (decided from the options alone: a flag-off run loads nothing more)."""
    from ...runtime.compile import check_compile_mode
    from .upstream_text import cache_capacity_from_env

    asked = ("sparse", "sparse_preset", "sparse_init_from", "sparse_text_encoder")
    return bool(any(getattr(args, name, None) for name in asked) or cache_capacity_from_env()
                or check_compile_mode(getattr(args, "sparse_compile", None)) != "none")


def sample_output_dir(args: Any) -> Optional[str]:
    """The folder MDM's ``sample.generate`` / ``sample.edit`` write ``results.npy`` to, derived from
    their parsed options as they derive it (absolute): ``--output_dir`` when given, else beside
    ``--model_path``: ``samples_<model folder>_<checkpoint number>_seed<seed>`` then
    ``_<text_prompt>`` / ``_<input_text file name>`` / ``_<dynamic_text_path file name>``
    (generate), or ``edit_<model folder>_<checkpoint number>_<edit_mode>_seed<seed>`` then
    ``_<text_condition>`` (edit). None for a command that samples into no folder
    (``eval.eval_humanml``: no ``--output_dir`` option) or without ``--model_path``."""
    out = getattr(args, "output_dir", None)
    model_path = getattr(args, "model_path", None)
    if out is None or not model_path:
        return None
    if out:
        return os.path.abspath(out)
    name = os.path.basename(os.path.dirname(model_path))
    niter = os.path.basename(model_path).replace("model", "").replace(".pt", "")
    seed = getattr(args, "seed", 10)

    def tag(text: str) -> str:
        return "_" + text.replace(" ", "_").replace(".", "")

    def file_tag(path: str) -> str:
        return tag(os.path.basename(path).replace(".txt", ""))

    if hasattr(args, "edit_mode"):
        out = os.path.join(os.path.dirname(model_path), f"edit_{name}_{niter}_{args.edit_mode}_seed{seed}")
        condition = getattr(args, "text_condition", "") or ""
        return os.path.abspath(out + (tag(condition) if condition else ""))
    out = os.path.join(os.path.dirname(model_path), f"samples_{name}_{niter}_seed{seed}")
    if getattr(args, "text_prompt", ""):
        out += tag(args.text_prompt)
    elif getattr(args, "input_text", ""):
        out += file_tag(args.input_text)
    elif getattr(args, "dynamic_text_path", ""):
        out += file_tag(args.dynamic_text_path)
    return os.path.abspath(out)


def _sparsify(model: Any, args: Any, data: Any, diffusion: Any, config: SparseConfig, start: Any = None) -> None:
    from ...integrations._rng import upstream_rng_untouched
    from ...integrations.start import Start, apply as apply_start, record_origin

    start = start if start is not None else Start(config=config)

    mean, std = dataset_mean_std(data)
    if mean is None and config.feature != "raw":
        warnings.warn("smdm: no dataset Mean/Std on the data loader; keyframes are selected on "
                      "normalised features", stacklevel=3)
    with upstream_rng_untouched():  # upstream's prompts / noise / batches stay those of a dense run
        apply_start(model, args, start, diffusion, mean, std, data)   # sparsify, or wrap / warm start
    from ...integrations.announce import announce_sparse_mode

    training = _is_training(args)
    announce_sparse_mode(model, "MDM/DiP", training)
    if not training:
        from ...integrations._files import record_sampling_output

        record_sampling_output(model, sample_output_dir(args))
        return
    steps = getattr(args, "diffusion_steps", None)
    if steps is None and diffusion is not None:
        from ...adapters.diffusion_wrapper import diffusion_steps

        steps = diffusion_steps(diffusion)
    warn_if_upstream_steps(config, steps)
    save_dir = args.save_dir
    if os.path.isdir(save_dir):  # sparse_config.json, and args.json's sparse_* as resolved (DiP prefix, steps)
        from ...integrations._files import record_run_config

        record_run_config(model, save_dir, args, os.path.join(save_dir, "args.json"),
                          overwrite=bool(getattr(args, "overwrite", False)))
        record_origin(args, os.path.join(save_dir, "args.json"))


def apply_compile(model: Any, args: Any, options_file: Optional[str] = None, diffusion: Any = None) -> Any:
    """``--sparse_compile`` (docs/compile.md): compile the model just built, dense or sparse, once,
    in place (``none`` / absent: nothing happens); when training with ``diffusion`` (one process:
    not under ``torchrun``, where DDP wraps the model and the model call is what is compiled) also
    the whole training step, ``diffusion.training_losses`` (its loss forward and backward); when
    training, on CUDA, upstream's optimizer step fused and its log read when it is read
    (:mod:`.upstream_optim`, under ``torchrun`` too); training and sampling, the diffusion's
    schedules read from device tables (:mod:`smdm_plugin.integrations.tables`); sampling, each
    step's timesteps filled on the device (:mod:`smdm_plugin.integrations.timesteps`). The
    setting that applies is printed and, when training, written to ``args.json``
    (``sparse_compile_applied``; ``options_file`` overrides where). Returns the
    :class:`~smdm_plugin.runtime.compile.CompileSetting` or None."""
    from ...integrations._files import compile_upstream
    from ...integrations.tables import tables_on_device
    from ...integrations.timesteps import timesteps_without_copy
    from ...runtime.compile import check_compile_mode

    training = _is_training(args)
    if options_file is None and training and os.path.isdir(args.save_dir):
        options_file = os.path.join(args.save_dir, "args.json")
    losses = optimizer = None
    mode = check_compile_mode(getattr(args, "sparse_compile", None))
    if diffusion is not None and mode != "none":
        tables_on_device(diffusion)     # training: the step's graph reads device tables; sampling: no copy per step
        if not training:
            timesteps_without_copy(diffusion)     # sampling: each step's timesteps filled on the device
    if training and diffusion is not None and hasattr(diffusion, "training_losses"):
        from .upstream_optim import fast_optimizer_step, train_device
        from .upstream_train import active

        if not active():
            from .prepare import loss_preparer

            losses = (diffusion, loss_preparer(model))
        optimizer = functools.partial(fast_optimizer_step, train_device(), mode, args)   # under torchrun too
    return compile_upstream(model, args, options_file, losses=losses, optimizer=optimizer)


def check_mdm_state_dict(model: Any, state_dict: Any, model_path: Optional[str] = None) -> None:
    """Raise a clear error when a sparse checkpoint meets a dense MDM (``--sparse`` lost, e.g. an
    ``args.json`` without the ``sparse`` keys) or the reverse; see
    :func:`smdm_plugin.io.checkpoint_files.check_state_dict`."""
    from ...io.checkpoint_files import check_state_dict, model_is_sparse, state_dict_is_sparse

    if model_is_sparse(model) and not state_dict_is_sparse(state_dict):
        from ...adapters.warm import is_dense_wrap

        if is_dense_wrap(model):
            return  # --sparse_preset: a dense checkpoint wrapped for sparse sampling (its weights load as they are)

    source = model_path or "checkpoint"
    if model_path and not model_is_sparse(model) and state_dict_is_sparse(state_dict):
        cfg = os.path.join(os.path.dirname(os.path.abspath(model_path)), CONFIG_FILENAME)
        if os.path.exists(cfg):
            source = f"{model_path} (with {CONFIG_FILENAME} beside it)"
    check_state_dict(model, state_dict, source)


# --------------------------------------------------------------------------- import hooks
def patch_model_options(mod: Any) -> None:
    """Wrap ``utils.parser_util.add_model_options`` (MDM and priorMDM): ``--sparse*`` join the
    ``model`` group, which ``args.json`` records and ``load_args_from_model`` restores."""
    def make(original):
        @functools.wraps(original)
        def add_model_options(parser):
            result = original(parser)
            group = next((g for g in parser._action_groups if g.title == "model"), None)
            add_sparse_options(group if group is not None else parser.add_argument_group("model"))
            return result
        return add_model_options

    wrap_once(mod, "add_model_options", make)


def patch_base_options(mod: Any) -> None:
    """Wrap ``utils.parser_util.add_base_options`` (MDM and priorMDM): ``--sparse_compile`` joins
    the ``base`` group, which ``load_args_from_model`` does not overwrite from ``args.json``."""
    def make(original):
        @functools.wraps(original)
        def add_base_options(parser):
            result = original(parser)
            from ...runtime.compile import add_compile_options

            group = next((g for g in parser._action_groups if g.title == "base"), parser)
            add_compile_options(group)
            return result
        return add_base_options

    wrap_once(mod, "add_base_options", make)


def _patch_model_util(mod: Any) -> None:
    def make_create(original):
        @functools.wraps(original)
        def create_model_and_diffusion(args, data, *a, **kw):
            model, diffusion = original(args, data, *a, **kw)
            sparsify_mdm(model, args, data, diffusion)
            return model, diffusion
        return create_model_and_diffusion

    def make_load(original):
        @functools.wraps(original)
        def load_model_wo_clip(model, state_dict, *a, **kw):
            check_mdm_state_dict(model, state_dict)
            return original(model, state_dict, *a, **kw)
        return load_model_wo_clip

    wrap_once(mod, "create_model_and_diffusion", make_create)
    wrap_once(mod, "load_model_wo_clip", make_load)  # load_saved_model looks it up here


def install_hooks() -> None:
    """Wrap MDM's ``utils.parser_util.add_model_options`` and ``utils.model_util``'s
    ``create_model_and_diffusion`` / ``load_model_wo_clip`` as they are imported (idempotent).
    Modules that do ``from utils.model_util import create_model_and_diffusion`` get the wrapped
    function because the wrap happens right after ``utils.model_util`` executes. Then the
    extensions: the guidance wrapper compiled whole (:mod:`.upstream_guidance`), text encoders
    (:mod:`.upstream_text`), multi-process training (:mod:`.upstream_train`),
    keyframe in-betweening in ``sample.edit`` (:mod:`.upstream_edit`); the plugin's warnings shown as
    ``smdm:`` lines (:mod:`smdm_plugin.integrations.messages`)."""
    from . import upstream_edit as mdm_edit, upstream_guidance as mdm_guidance, upstream_text as mdm_text
    from . import upstream_train as mdm_train
    from ...integrations._hooks import on_import
    from ...integrations.messages import show_plugin_warnings

    show_plugin_warnings()
    on_import("utils.parser_util", patch_model_options)
    on_import("utils.parser_util", patch_base_options)
    on_import("utils.model_util", _patch_model_util)
    mdm_guidance.install_hooks("utils.sampler_util")    # (older checkouts: model.cfg_sampler)
    mdm_guidance.install_hooks("model.cfg_sampler")
    for extension in (mdm_text, mdm_train, mdm_edit):
        extension.install_hooks()


#: the upstream checkout `smdm run` hooks (this family's FamilySpec names it)
INTEGRATION = Integration(
    "mdm", detect=is_mdm_repo, install_hooks=install_hooks, priority=0,
    layout="model/mdm.py + utils/model_util.py (MDM/DiP)")
