"""One line in the user's own run (upstream's log) saying that sparse keyframe mode is on and what the
run does with it, per phase: the files beside the checkpoint say it too, but a user reading the
training or sampling log should not have to look there.

    smdm: sparse keyframe mode ON (MDM/DiP, sampling): reduction 0.8 (80% of the frames dropped);
    sampling: uniform keyframes at every step (dynamic update off), linear fill; FSQ keys off,
    Lipschitz MLPs off, T 50

A training run states both phases (its checkpoint samples with the same settings); a sampling run
only what sampling does: the keyframe selector and the mask noise act on training only.
"""
from __future__ import annotations

import sys
import weakref
from typing import Any, Optional

from ..core.config import SparseConfig

_ANNOUNCED: "weakref.WeakSet[Any]" = weakref.WeakSet()  # models already announced (nothing put on them)
_ONOFF = {True: "on", False: "off"}


def motion_features(model: Any) -> Optional[int]:
    """The number of features ``D`` of the motions ``model`` denoises (MDM: ``njoints * nfeats``,
    MotionDiffuse: ``input_feats``), None when it does not say."""
    d = getattr(model, "input_feats", None)
    if d is None and getattr(model, "njoints", None) is not None:
        d = int(model.njoints) * int(getattr(model, "nfeats", 1) or 1)
    return int(d) if isinstance(d, int) and not isinstance(d, bool) else None


def training_phase(config: SparseConfig) -> str:
    """What training does: keyframes chosen on x0 by the selector, the mask noise, the loss."""
    noise = f"mask noise {config.mask_noise:g}" if config.mask_noise else "no mask noise"
    loss = "" if config.interpolate else ", loss on keyframes only"
    return f"training: {config.selector} keyframes from x0, {noise}{loss}"


def sampling_phase(config: SparseConfig, late_steps: int, features: Optional[int]) -> str:
    """What sampling does: the mask schedule (uniform, and the selector on x_t in the last
    ``late_steps`` steps), how the other frames are filled (``features``: D, to resolve ``auto``)."""
    T = config.diffusion_steps
    if config.reduction == 0:
        return "sampling: every frame a keyframe"
    if late_steps:
        schedule = f"uniform keyframes, then {config.selector} on x_t in the last {late_steps} of {T} steps"
    else:
        schedule = "uniform keyframes at every step (dynamic update off)"
    if features is not None:
        fill = config.sample_fill(features)
    elif config.sample_interpolation == "auto":
        fill = "auto (linear for HumanML3D/KIT features, cubic for raw)"
    else:
        fill = config.sample_interpolation
    if fill == "cubic" and config.sample_interpolation_steps is not None:
        fill = f"cubic in the last {config.sample_interpolation_steps} steps, linear before"
    return f"sampling: {schedule}, {fill} fill"


def model_parts(config: SparseConfig) -> str:
    """The layers the sparse model runs with, its step count, prefix and text encoder."""
    lipschitz = f"Lipschitz MLPs {_ONOFF[config.lipschitz]}" + (f" (λ {config.lipschitz_lambda:g})"
                                                                if config.lipschitz else "")
    parts = [f"FSQ keys {_ONOFF[config.fsq]}", lipschitz, f"T {config.diffusion_steps}"]
    if config.prefix_frames:
        parts.append(f"{config.prefix_frames} prefix frames dense")
    if config.text_encoder:
        parts.append(f"text encoder {config.text_encoder}")
    return ", ".join(parts)


def describe_run(config: SparseConfig, training: bool, late_steps: int, features: Optional[int] = None) -> str:
    """``reduction R (P% of the frames dropped); [training: ...;] sampling: ...; <model parts>``: what the
    run does."""
    r = config.reduction
    phases = [f"reduction {r:g} ({r:.0%} of the frames dropped)"] + ([training_phase(config)] if training else [])
    return "; ".join(phases + [sampling_phase(config, late_steps, features), model_parts(config)])


def announce_sparse_mode(model: Any, family: str, training: bool) -> None:
    """Print ``smdm: sparse keyframe mode ON (<family>, training|sampling): <what the run does>``
    to stderr once per model (:func:`describe_run` of the settings the model runs with; its own
    mask schedule); nothing for a dense model."""
    from ..adapters.state import find_sparse_model, get_state

    sparse = find_sparse_model(model)
    if sparse is None or model in _ANNOUNCED:
        return
    state = get_state(sparse)
    what = describe_run(state.config, training, state.schedule.late_steps, motion_features(sparse))
    print(f"smdm: sparse keyframe mode ON ({family}, {'training' if training else 'sampling'}): {what}",
          file=sys.stderr, flush=True)
    _ANNOUNCED.add(model)
