"""Upstream MDM / DiP / priorMDM: start sparse from a dense checkpoint."""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from typing import Any, NoReturn, Optional

from ..core.config import SparseConfig
from .options import INIT_OPTION, PRESET_OPTION


def _fail(option: str, message: str) -> "NoReturn":
    """An argparse-style error naming the option: one line on stderr, exit status 2."""
    sys.stderr.write(f"error: argument {option}: {message}\n")
    raise SystemExit(2)


@dataclass
class Start:
    """How the model becomes sparse: ``wrap`` (a dense checkpoint sampled sparse), ``warm`` (dense
    weights from ``init_from`` + fitted new layers), or neither (plain ``sparsify``)."""

    config: SparseConfig
    wrap: bool = False
    init_from: Optional[str] = None
    preset: Optional[str] = None


def resolve(args: Any, config: SparseConfig, training: bool) -> Start:
    """The sparse settings and start of this run: ``--sparse_preset`` replaces the ``--sparse*``
    settings (training, or sampling a dense checkpoint; a sparse checkpoint keeps its own and the
    option is ignored with a warning); ``--sparse_init_from`` only when training."""
    preset = getattr(args, "sparse_preset", None)
    init_from = getattr(args, "sparse_init_from", None) if training else None
    if preset and not (training or not config.enabled):
        import warnings

        warnings.warn(f"smdm: {PRESET_OPTION} {preset}: the checkpoint is already sparse; its own settings are used")
        preset = None
    if preset:
        from ..core.presets import load_preset

        try:
            config = load_preset(preset).replace(enabled=True)
        except (FileNotFoundError, ValueError) as e:
            _fail(PRESET_OPTION, str(e))
    elif init_from and not config.enabled:
        _fail(INIT_OPTION, f"sparse training only (add --sparse or {PRESET_OPTION})")
    if init_from and not os.path.isfile(init_from):
        _fail(INIT_OPTION, f"no such checkpoint file: {init_from!r}")
    wrap = bool(preset) and not training
    if wrap:
        from ..adapters.warm import adds_layers

        if adds_layers(config):
            _fail(PRESET_OPTION, f"{preset} adds layers a dense checkpoint has no weights for (lipschitz="
                                 f"{config.lipschitz}, fsq={config.fsq}); use zero_shot, or warm-start a sparse "
                                 f"training with {INIT_OPTION}")
    return Start(config=config, wrap=wrap, init_from=init_from, preset=preset)


def apply(model: Any, args: Any, start: Start, diffusion: Any, mean: Any, std: Any, data: Any = None) -> Any:
    """Make ``model`` sparse as ``start`` says (wrap, warm start or plain ``sparsify``); a training
    loop that resumes it loads a 0.9 run's optimizer state too (:mod:`.resume`)."""
    from ..adapters.surgery import sparsify
    from ..adapters.warm import wrap_dense
    from .resume import install_hooks

    install_hooks()

    if start.wrap:
        origin = getattr(args, "model_path", None)
        wrap_dense(model, start.config, diffusion=diffusion, mean=mean, std=std, origin=origin)
        print(f"smdm: wrapped the DENSE checkpoint {origin or '(model)'} for sparse sampling (preset {start.preset}: "
              f"{start.config.reduction:.0%} of the frames dropped, Lipschitz layers "
              f"{'on' if start.config.lipschitz else 'off'}, FSQ keys {'on' if start.config.fsq else 'off'}; "
              "trained weights unchanged)", flush=True)
        return model
    if start.init_from:
        origin = warm_start_upstream(model, start, diffusion, mean, std, data)
        setattr(args, "sparse_init_origin", origin)
        print(f"smdm: initialised from the dense checkpoint {origin['path']} ({origin['digest'][:19]}...); "
              f"{origin['fit_summary']}", flush=True)
        return model
    return sparsify(model, start.config, diffusion=diffusion, mean=mean, std=std)


def warm_start_upstream(model: Any, start: Start, diffusion: Any, mean: Any, std: Any, data: Any) -> dict:
    """Load ``start.init_from`` (dense) into the freshly built upstream model (CLIP weights, not in
    MDM's checkpoints, may be missing; nothing else), then :func:`~smdm_plugin.adapters.warm.warm_start`
    with a probe on one batch of the training data (upstream's random streams untouched)."""
    from ..adapters.warm import file_digest, warm_start
    from ..io.checkpoint_files import read_state_dict, state_dict_is_sparse, unwrap_state_dict
    from ._rng import upstream_rng_untouched

    path = start.init_from
    sd = unwrap_state_dict(read_state_dict(path))
    if state_dict_is_sparse(sd):
        _fail(INIT_OPTION, f"{path} holds a sparse model (start from a dense one)")
    missing, unexpected = model.load_state_dict(sd, strict=False)
    bad = [k for k in missing if not k.startswith("clip_model.")] + list(unexpected)
    if bad:
        _fail(INIT_OPTION, f"{path} does not fit the model (e.g. {bad[0]!r}); pass the model options it was "
                           "trained with")
    with upstream_rng_untouched():
        probe = _data_probe(data, diffusion, model)
        report = warm_start(model, start.config, probe, diffusion=diffusion, mean=mean, std=std)
    return {"path": os.path.abspath(path), "digest": file_digest(path), "fit": report.to_dict(),
            "fit_summary": report.summary()}


def _data_probe(data: Any, diffusion: Any, model: Any):
    """A :func:`~smdm_plugin.adapters.warm.diffusion_probe` on the first batch of upstream's loader
    (``(motion [B, D, 1, N], {'y': ...})``); a random-normal batch when there is none."""
    import torch

    from ..adapters.warm import diffusion_probe

    x0, cond = None, None
    if data is not None:
        try:
            x0, cond = next(iter(data))
        except (StopIteration, TypeError, ValueError):
            x0 = None
    if x0 is None:
        D = int(getattr(model, "njoints", 263)) * int(getattr(model, "nfeats", 1))
        x0, cond = torch.randn(4, int(getattr(model, "njoints", D)), int(getattr(model, "nfeats", 1)), 60), \
            {"y": {"mask": torch.ones(4, 1, 1, 60, dtype=torch.bool), "lengths": torch.full((4,), 60)}}
    return diffusion_probe(x0, cond, diffusion.q_sample, int(diffusion.num_timesteps))


def record_origin(args: Any, args_json: str) -> None:
    """Add ``sparse_init_origin`` (path, digest, fit errors) to the run's ``args.json`` (atomic)."""
    import json

    from ..support.atomic import atomic_write_json

    origin = getattr(args, "sparse_init_origin", None)
    if not origin or not os.path.isfile(args_json):
        return
    with open(args_json, encoding="utf-8") as f:
        doc = json.load(f)
    if isinstance(doc, dict) and doc.get("sparse_init_origin") != origin:
        doc["sparse_init_origin"] = origin
        atomic_write_json(args_json, doc, indent=4, sort_keys=True)
