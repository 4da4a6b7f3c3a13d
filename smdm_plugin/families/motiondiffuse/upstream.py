"""MotionDiffuse (text2motion/) integration: ``--sparse*`` options, sparsify the
``MotionTransformer`` where ``DDPMTrainer`` receives it, sparse-mode loss terms (``+ L_lip``;
keyframes only for the ``interpolate=False`` ablation) in ``DDPMTrainer.backward_G``."""
from __future__ import annotations

import functools
import os
from typing import Any, Optional

import numpy as np

from ...core.config import SparseConfig
from ...support.config_files import CONFIG_FILENAME
from ...integrations._hooks import wrap_once
from ...integrations.options import add_sparse_options as _add_sparse_options, with_family_defaults
from ...integrations.checkouts import Integration

FAMILY = "motiondiffuse"


def add_sparse_options(parser: Any) -> Any:
    """``--sparse`` / ``--sparse_<field>`` on MotionDiffuse's option parser, with MotionDiffuse's own
    defaults (:data:`~smdm_plugin.integrations.options.FAMILY_DEFAULTS`: ``--sparse_fsq false``, its
    self-attention is linear); what ``patches/motiondiffuse.patch`` and the hooks call."""
    return _add_sparse_options(parser, family=FAMILY)


def _coerce(value: Any, default: Any) -> Any:
    """``opt.txt`` values come back as str/int/float (utils/get_opt.py); fix them up."""
    if isinstance(value, str):
        s = value.strip()
        if s == "None":
            return None
        if isinstance(default, tuple) and s.startswith("["):
            return tuple(int(v) for v in s.strip("[]()").split(",") if v.strip())
        if isinstance(default, bool):
            return s == "True"
        if isinstance(default, float):
            return float(s)
        if isinstance(default, int):
            return int(float(s))
    if isinstance(default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def config_from_opt(opt: Any) -> SparseConfig:
    """The sparse config of a MotionDiffuse run: ``<model_dir>/sparse_config.json`` when not
    training and present, else the ``sparse*`` options of ``opt`` (argparse or ``get_opt``)."""
    model_dir = getattr(opt, "model_dir", None)
    if not getattr(opt, "is_train", False) and model_dir:
        path = os.path.join(model_dir, CONFIG_FILENAME)
        if os.path.exists(path) and not getattr(opt, "_smdm_cli_override", False):
            saved = SparseConfig.load(path)
            if _coerce(getattr(opt, "sparse", False), False):  # opt.txt describes the same model: it must agree
                from ...core.agreement import SET_WHEN_ATTACHED, disagreement

                opt_file = os.path.join(os.path.dirname(os.path.normpath(model_dir)), "opt.txt")
                why = disagreement(saved, _options(opt), path, opt_file, ignore=(*SET_WHEN_ATTACHED, "fsq"))
                if why:
                    raise ValueError(why)
            return saved
    return SparseConfig.from_args(_options(opt))


def _options(opt: Any) -> dict:
    """``opt``'s ``sparse``/``sparse_*`` options with their types restored."""
    d = with_family_defaults(vars(opt), FAMILY)
    defaults = SparseConfig(enabled=False).to_dict()
    for k, v in defaults.items():
        key = f"sparse_{k}"
        if key in d:
            d[key] = _coerce(d[key], tuple(v) if isinstance(v, list) else v)
    d["sparse"] = bool(_coerce(d.get("sparse", False), False))
    d.pop("sparse_version", None)
    return d


def merge_sparse_options(opt: Any, args: Any) -> Any:
    """Visualisation: ``--sparse*`` given on its command line win over the checkpoint's."""
    if getattr(args, "sparse", False):
        for k, v in vars(args).items():
            if k == "sparse" or k.startswith("sparse_"):
                setattr(opt, k, v)
        opt._smdm_cli_override = True
    return opt


def mean_std_from_opt(opt: Any):
    """The statistics the denoiser's inputs are normalised with."""
    from .model import training_mean_std

    meta = getattr(opt, "meta_dir", None)
    if not getattr(opt, "is_train", False) and meta and os.path.exists(os.path.join(meta, "mean.npy")):
        return np.load(os.path.join(meta, "mean.npy")), np.load(os.path.join(meta, "std.npy"))
    root = getattr(opt, "data_root", None)
    if root and os.path.exists(os.path.join(root, "Mean.npy")):
        mean, std = np.load(os.path.join(root, "Mean.npy")), np.load(os.path.join(root, "Std.npy"))
        joints = int(getattr(opt, "joints_num", 22))
        return training_mean_std(mean, std, float(getattr(opt, "feat_bias", 25.0)), joints)
    return None, None


def attach_trainer(trainer: Any, config: Optional[SparseConfig] = None) -> Any:
    """Sparsify ``trainer.encoder`` (or its ``.module``) and wrap ``trainer.diffusion`` according
    to ``trainer.opt``; training runs save the config beside the checkpoints and bring ``opt``
    and ``opt.txt``'s ``sparse*`` entries to the settings that ran."""
    from ...adapters.surgery import is_sparse, sparsify
    from ...integrations._rng import upstream_rng_untouched

    from ...integrations.messages import show_plugin_warnings

    show_plugin_warnings()
    opt = trainer.opt
    config = config if config is not None else config_from_opt(opt)
    enc = trainer.encoder
    core = getattr(enc, "module", enc)
    if config.enabled and not is_sparse(core):
        mean, std = mean_std_from_opt(opt)
        with upstream_rng_untouched():  # upstream's batches / noise stay those of a dense run
            sparsify(core, config, mean=mean, std=std, diffusion=trainer.diffusion, family=FAMILY)
        from ...integrations.announce import announce_sparse_mode

        announce_sparse_mode(core, "MotionDiffuse", bool(getattr(opt, "is_train", False)))
    if config.enabled:
        from .upstream_loop import mask_without_loop

        mask_without_loop(core)   # the trainer's padding mask in two ops (upstream: one write per frame)
    if config.enabled and getattr(opt, "is_train", False) and getattr(opt, "model_dir", None):
        # sparse_config.json (never replacing another config unasked), and opt.txt's sparse_* as
        # they ran (e.g. sparse_fsq False: FSQ keys cannot apply to linear attention, with a warning)
        from ...integrations._files import record_run_config

        opt_file = os.path.join(os.path.dirname(os.path.normpath(opt.model_dir)), "opt.txt")
        record_run_config(core, opt.model_dir, opt, opt_file)
    return trainer


class _OptimFused:
    """``torch.optim`` as MotionDiffuse's trainer module reads it (``optim.Adam(...)`` in
    ``DDPMTrainer.train``), its ``Adam`` fused (:class:`~smdm_plugin.runtime.fused_optim.FusedAdam`)."""

    def __init__(self) -> None:
        from ...runtime.fused_optim import FusedAdam

        self.Adam = FusedAdam

    def __getattr__(self, name: str) -> Any:
        import torch.optim

        return getattr(torch.optim, name)


#: what a training run whose Adam is fused records beside its compile setting (``opt.txt``)
OPTIMIZER_NOTE = ("optimizer step: Adam fused; loss logged without a sync, batches, lengths and timesteps "
                  "copied without one")
#: the note where ``backward_G`` is upstream's own (``patches/motiondiffuse.patch``): it reads the loss
LOSS_READ_NOTE = ("optimizer step: Adam fused; batches, lengths and timesteps copied without a sync "
                  "(the loss read each step: upstream's backward_G)")


def fuse_trainer_optimizer(trainer: Any, device: Any, mode: Any) -> Optional[str]:
    """A compiled training run's step after the loss: where
    :func:`~smdm_plugin.runtime.compile.fused_optimizer_kwargs` says the fused optimizer applies
    (CUDA), the ``Adam`` that ``DDPMTrainer.train`` builds is fused (kept fused across
    ``--is_continue``) and the loop makes no host sync per step
    (:func:`~.upstream_loop.loop_without_sync`). Returns :data:`OPTIMIZER_NOTE` (through the patch:
    :data:`LOSS_READ_NOTE`), or None (nothing changed)."""
    import sys

    import torch.optim

    from ...runtime import compile as compile_mod

    module = sys.modules.get(type(trainer).__module__)
    if device is None or module is None or not compile_mod.fused_optimizer_kwargs(device, mode).get("fused"):
        return None
    if getattr(module, "optim", None) is torch.optim:
        module.optim = _OptimFused()
    if not isinstance(getattr(module, "optim", None), _OptimFused):
        return None
    from .upstream_loop import loop_without_sync

    hooked = loop_without_sync(trainer, device)   # no host sync per step (families/motiondiffuse/upstream_loop.py)
    return OPTIMIZER_NOTE if "loss" in hooked else LOSS_READ_NOTE


def compile_trainer(trainer: Any) -> Any:
    """``--sparse_compile`` (docs/compile.md): compile ``trainer.encoder`` (inside its DDP /
    DataParallel wrapper), dense or sparse, once, in place; a training run's Adam fused on CUDA
    (:func:`fuse_trainer_optimizer`); the diffusion's schedules read from device tables
    (:mod:`smdm_plugin.integrations.tables`), sampling runs' timesteps made on the device
    (:mod:`smdm_plugin.integrations.timesteps`), the padding mask without a loop
    (:func:`~.upstream_loop.mask_without_loop`); training runs write the setting that applies to ``opt.txt``
    (``sparse_compile``, ``sparse_compile_applied``). ``none`` / absent: nothing happens. Returns
    the :class:`~smdm_plugin.runtime.compile.CompileSetting` or None."""
    from ...integrations._files import compile_upstream
    from ...integrations.tables import tables_on_device
    from ...runtime.compile import check_compile_mode

    opt = trainer.opt
    core = getattr(trainer.encoder, "module", trainer.encoder)
    device = getattr(trainer, "device", None) or getattr(opt, "device", None)
    mode = check_compile_mode(getattr(opt, "sparse_compile", None))
    if mode != "none" and getattr(trainer, "diffusion", None) is not None:
        tables_on_device(trainer.diffusion)   # its loss and sampling steps copy no schedule per call
    if mode != "none":
        from .upstream_loop import mask_without_loop

        mask_without_loop(core)   # dense too: its denoiser's padding mask traces (no loop over frames)
        if not getattr(opt, "is_train", False) and getattr(trainer, "diffusion", None) is not None:
            from ...integrations.timesteps import timesteps_without_copy

            timesteps_without_copy(trainer.diffusion)   # sampling: each step's timesteps filled on the device
    options_file = optimizer = None
    if getattr(opt, "is_train", False):
        optimizer = functools.partial(fuse_trainer_optimizer, trainer, device, mode)
        if getattr(opt, "model_dir", None):
            options_file = os.path.join(os.path.dirname(os.path.normpath(opt.model_dir)), "opt.txt")
    return compile_upstream(core, opt, options_file, device=device, optimizer=optimizer)


def add_options(parser: Any) -> Any:
    """``--sparse*`` and ``--sparse_compile`` (what the hooks add to MotionDiffuse's option parsers)."""
    from ...runtime.compile import add_compile_options

    add_sparse_options(parser)
    return add_compile_options(parser)


# --------------------------------------------------------------------------- import hooks
def _patch_options(mod, cls_name: str) -> None:
    def make(original):
        @functools.wraps(original)
        def initialize(self):
            original(self)
            add_options(self.parser)
        return initialize

    wrap_once(getattr(mod, cls_name, None), "initialize", make)


def _cpu_fallback(opt: Any) -> None:
    """``tools/train.py`` sets ``opt.device = cuda`` unconditionally; without CUDA use the CPU
    (what the patch's change to ``tools/train.py`` does)."""
    import torch

    dev = getattr(opt, "device", None)
    if dev is not None and torch.device(dev).type == "cuda" and not torch.cuda.is_available():
        opt.device = torch.device("cpu")


def _patch_trainer(mod) -> None:
    def make_init(init):
        @functools.wraps(init)
        def __init__(self, args, encoder, *a, **kw):
            _cpu_fallback(args)
            init(self, args, encoder, *a, **kw)
            if getattr(args, "sparse", False):
                attach_trainer(self)
                self.to(self.device)
            compile_trainer(self)  # --sparse_compile, dense or sparse (none: nothing)
        return __init__

    def make_backward(backward):
        @functools.wraps(backward)
        def backward_G(self):
            from .upstream_loop import deferring, log_of, upstream_loss

            sparse = getattr(self.opt, "sparse", False)
            if not sparse and not deferring(self):
                return backward(self)
            loss = upstream_loss(self)           # upstream's loss, the same ops (read once, or later)
            if sparse:
                from .model import trainer_loss

                loss = trainer_loss(self, loss)
            self.loss_mot_rec = loss
            return log_of(self, loss)
        return backward_G

    cls = getattr(mod, "DDPMTrainer", None)
    wrap_once(cls, "__init__", make_init)
    wrap_once(cls, "backward_G", make_backward)


def install_hooks() -> None:
    """Wrap MotionDiffuse's option classes and ``DDPMTrainer`` as they are imported (run from
    ``text2motion/``). Idempotent; do not combine with the patch."""
    from ...integrations._hooks import on_import
    from ...integrations.messages import show_plugin_warnings

    show_plugin_warnings()
    on_import("options.train_options", lambda m: _patch_options(m, "TrainCompOptions"))
    on_import("options.evaluate_options", lambda m: _patch_options(m, "TestOptions"))
    on_import("trainers.ddpm_trainer", _patch_trainer)


def is_motiondiffuse_repo(path: str) -> bool:
    """A MotionDiffuse checkout: the repository root (has ``text2motion/``) or that folder
    (``trainers/ddpm_trainer.py`` + ``models/transformer.py``; ``tools/train.py``'s cwd)."""
    j = os.path.join
    return os.path.isdir(j(path, "text2motion")) or (
        os.path.isfile(j(path, "trainers", "ddpm_trainer.py")) and os.path.isfile(j(path, "models", "transformer.py")))


#: the upstream checkout `smdm run` hooks (this family's FamilySpec names it)
INTEGRATION = Integration(
    "motiondiffuse", detect=is_motiondiffuse_repo, install_hooks=install_hooks, priority=20,
    layout="text2motion/ (MotionDiffuse, root or that folder)")
