"""Every file a sparse run writes states the settings that ran, and every sparse sampling run leaves
its settings beside its samples (:func:`record_sampling_output`).

Upstream writes its options (MDM / DiP / priorMDM ``args.json``, MotionDiffuse ``opt.txt``) before
the model is built; sparsify then resolves some settings from the model and diffusion (DiP's dense
prefix, the diffusion steps, MotionDiffuse's FSQ keys that cannot apply). The integrations call
:func:`record_run_config` right after sparsify: it writes ``sparse_config.json`` beside the weights
and rewrites the ``sparse`` / ``sparse_*`` entries of the options file (atomically, other entries
untouched) and of the parsed options with the resolved config, so the files agree.
"""
from __future__ import annotations

import json
import os
from typing import Any, Callable, Dict, Optional, Tuple

from ..support.atomic import atomic_write_json, atomic_write_text
from ..core.config import SparseConfig
from ..support.config_files import CONFIG_FILENAME

OPT_END = "-------------- End ----------------"  # closes upstream's options block in opt.txt


def resolved_options(config: SparseConfig) -> Dict[str, Any]:
    """``sparse`` / ``sparse_<field>`` entries of ``config`` as parsed options (tuples as lists)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in config.to_args_dict().items()
            if k != "sparse_version"}


def update_namespace(args: Any, config: SparseConfig) -> None:
    """Set the parsed options' ``sparse*`` attributes that exist on ``args`` to ``config``'s."""
    d = vars(args) if hasattr(args, "__dict__") else None
    if d is None:
        return
    for k, v in resolved_options(config).items():
        if k in d:
            setattr(args, k, v)


def update_args_json(path: str, config: SparseConfig) -> bool:
    """Rewrite the ``sparse*`` entries of MDM's ``args.json`` at ``path`` (present keys only, plus
    ``sparse``); False when the file is absent. Atomic."""
    return set_json_entries(path, resolved_options(config), add=("sparse",))


def set_json_entries(path: str, values: Dict[str, Any], add: Any = None) -> bool:
    """Rewrite entries of a JSON options file (``args.json``): the keys of ``values`` present in
    it, and those of ``add`` (all of them when None); False when the file is absent. Atomic."""
    if not os.path.isfile(path):
        return False
    with open(path, encoding="utf-8") as f:
        data = json.load(f)
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object of options, got {type(data).__name__}")
    new = dict(data)
    for k, v in values.items():
        if k in data or add is None or k in add:
            new[k] = v
    if new != data:
        atomic_write_json(path, new, indent=4, sort_keys=True)
    return True


def update_opt_txt(path: str, config: SparseConfig) -> bool:
    """Rewrite the ``sparse*`` lines (``key: value``) of MotionDiffuse's ``opt.txt``; lines of
    other options are kept byte for byte; absent ``sparse*`` keys are added before the end line.
    False when the file is absent. Atomic."""
    return set_opt_entries(path, resolved_options(config))


def set_opt_entries(path: str, options: Dict[str, Any]) -> bool:
    """Rewrite (or add before the end line) ``key: value`` lines of MotionDiffuse's ``opt.txt``;
    other lines byte for byte. False when the file is absent. Atomic."""
    if not os.path.isfile(path):
        return False
    with open(path, encoding="utf-8") as f:
        lines = f.read().splitlines()
    values = {k: str(v) for k, v in options.items()}
    out, seen = [], set()
    for line in lines:
        key = line.split(":", 1)[0].strip() if ":" in line else None
        if key in values:
            out.append(f"{key}: {values[key]}")
            seen.add(key)
        elif line.strip() == OPT_END:
            out.extend(f"{k}: {v}" for k, v in values.items() if k not in seen)
            seen.update(values)
            out.append(line)
        else:
            out.append(line)
    out.extend(f"{k}: {v}" for k, v in values.items() if k not in seen)
    text = "\n".join(out) + "\n"
    if text != "\n".join(lines) + "\n":
        atomic_write_text(path, text)
    return True


def record_run_config(model: Any, weights_dir: str, args: Any, options_file: Optional[str],
                      overwrite: bool = False) -> SparseConfig:
    """After sparsify: ``sparse_config.json`` in ``weights_dir``, the resolved ``sparse*`` options
    in ``args`` and in ``options_file`` (``args.json`` or ``opt.txt``; skipped when None/absent).
    Returns the config that ran."""
    from ..adapters.state import sparse_config_of
    from ..adapters.checkpoint import save_sparse_config

    config = sparse_config_of(model)
    if config is None:
        raise ValueError("record_run_config: the model is not sparse")
    save_sparse_config(config, weights_dir, overwrite=overwrite)
    update_namespace(args, config)
    if options_file:
        (update_opt_txt if options_file.endswith(".txt") else update_args_json)(options_file, config)
    return config


def record_compile(args: Any, setting: Any, options_file: Optional[str], also: Optional[str] = None) -> bool:
    """After :func:`~smdm_plugin.runtime.compile.compile_from_args`: ``sparse_compile`` and
    ``sparse_compile_applied`` (``setting.describe()``: what runs, and why it differs from what was
    asked; then ``also``, when given, after ``; ``) into the run's options file (``args.json`` or
    ``opt.txt``; written by upstream before the model is built). False when there is no such file
    or nothing to record."""
    if setting is None or not options_file:
        return False
    applied = setting.describe() + (f"; {also}" if also else "")
    values = {"sparse_compile": getattr(args, "sparse_compile", "none"), "sparse_compile_applied": applied}
    if options_file.endswith(".txt"):
        return set_opt_entries(options_file, values)
    return set_json_entries(options_file, values)


def compile_upstream(model: Any, args: Any, options_file: Optional[str] = None, *, device: Any = None,
                     losses: Optional[Tuple[Any, Callable]] = None,
                     optimizer: Optional[Callable[[], Optional[str]]] = None) -> Any:
    """``--sparse_compile`` in an upstream run (docs/compile.md), the one helper of every family's
    hooks: compile ``model`` (dense or sparse) once, in place; with ``losses`` (``(diffusion,
    prepare)``: a training run whose loss is ``diffusion.training_losses``) also the whole training
    step (:func:`~smdm_plugin.runtime.compile.compile_training_losses`). Print the setting that
    applies and write it to ``options_file`` (``args.json`` / ``opt.txt``; None: nowhere; the
    training step's when it is captured); ``optimizer`` (a training run): called once compiled,
    returns what it changed of upstream's optimizer step (recorded after the setting) or None.
    ``none`` / absent: nothing happens. Returns the
    :class:`~smdm_plugin.runtime.compile.CompileSetting` that applies (the training step's, when
    captured) or None."""
    import sys

    from ..runtime.compile import compile_from_args, compile_losses_from_args
    from .messages import show_plugin_warnings

    show_plugin_warnings()
    setting = compile_from_args(model, args, device=device)
    if setting is None:
        return None
    sys.stderr.write(f"smdm: {type(model).__name__} runs {setting.describe()}\n")
    if losses is not None:
        step = compile_losses_from_args(losses[0], model, args, losses[1], device=device)
        if step is not None:
            sys.stderr.write(f"smdm: the training step runs {step.describe()}\n")
            setting = step
    also = optimizer() if optimizer is not None else None
    if also:
        sys.stderr.write(f"smdm: {also}\n")
    record_compile(args, setting, options_file, also=also)
    return setting


#: the file upstream's sampling scripts (MDM ``sample.generate`` / ``sample.edit``, priorMDM
#: ``sample.double_take``) write their samples to
RESULTS_FILE = "results.npy"


def record_sampling_output(model: Any, out_dir: Optional[str]) -> None:
    """A sparse sampling run states its settings beside its outputs: when the process ends,
    ``sparse_config.json`` (the model's config) goes into ``out_dir``, the folder the run writes
    ``results.npy`` to (upstream replaces that folder at the end of sampling, so it cannot be
    written earlier). Written atomically, and only when ``out_dir`` holds a ``results.npy`` of this
    run (nothing when sampling failed or the script wrote no samples there); a ``sparse_config.json``
    already there with other settings is left as it is, with a warning naming it."""
    import atexit
    import time
    import warnings

    from ..adapters.state import sparse_config_of

    config, since = sparse_config_of(model), time.time() - 1.0
    if config is None or not out_dir:
        return

    def write() -> None:
        from ..adapters.checkpoint import save_sparse_config

        results = os.path.join(out_dir, RESULTS_FILE)
        if not os.path.isfile(results) or os.path.getmtime(results) < since:
            return
        try:
            save_sparse_config(config, out_dir)
        except (OSError, ValueError) as e:
            warnings.warn(f"smdm: {CONFIG_FILENAME} not written beside {results}: {e}")

    atexit.register(write)
