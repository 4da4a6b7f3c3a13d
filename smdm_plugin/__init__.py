"""smdm-plugin: sparse keyframe mode ("Less is More", sMDM) for MDM-family motion diffusion code."""
from __future__ import annotations

import importlib
import sys
from typing import TYPE_CHECKING, Any, Dict, List


__version__ = "0.10.7"

_EXPORTS: Dict[str, str] = {
    # the method's settings
    "SparseConfig": "core.config", "load_preset": "core.presets", "ConfigTypeError": "support.values",
    "select_keyframes": "core.selection", "register_selector": "core.selection",
    "register_backend": "core.attention_backends", "available_backends": "core.attention_backends",
    # a model made sparse, in place and reversibly
    "sparsify": "adapters.surgery", "unsparsify": "adapters.surgery", "is_sparse": "adapters.surgery",
    "set_mean_std": "adapters.surgery", "sparse_config_of": "adapters.state",
    "wrap_dense": "adapters.warm", "warm_start": "adapters.warm",
    "attach_diffusion": "adapters.diffusion_wrapper", "detach_diffusion": "adapters.diffusion_wrapper",
    "KeyframeRequest": "adapters.request", "with_forced": "adapters.request",
    "keyframe_collate": "families.mdm.model",
    "save_sparse_config": "adapters.checkpoint", "load_checkpoint": "adapters.checkpoint",
    "sample_inbetween": "adapters.inbetween_sampling", "keyframe_constraint": "adapters.inbetween_sampling",
    "swap_text_encoder": "adapters.text_encoder", "install_text_cache": "adapters.text_cache",
    # a model family of one's own
    "register_family": "adapters.families", "FamilySpec": "adapters.families",
    "ModelFamily": "adapters.family", "CallInputs": "adapters.call",
    # graph capture
    "compile_model": "runtime.compile", "CompileSetting": "runtime.compile",
    # the in-package model and its trainer
    "TinyMDM": "reference.backbone", "SimpleDiffusion": "reference.simple_diffusion",
    "load_trained": "training.trainer",
    # measuring
    "Evaluator": "metrics.evaluator", "load_evaluator": "metrics.evaluator", "score_motions": "metrics.evaluator",
    "EvalResult": "metrics.evaluator",
    "read_bvh": "io.bvh", "load_cmu_clip": "io.bvh",
}

__all__: List[str] = sorted(_EXPORTS) + ["__version__"]



class _MovedPaths:
    """Last on ``sys.meta_path``, so asked only when no finder found a module: a module path 0.9
    moved fails with one line naming the new one (``support/moved.py``, loaded only then)."""

    @staticmethod
    def find_spec(name: str, path: Any = None, target: Any = None) -> None:
        if name.startswith(__name__ + "."):
            from .support.moved import moved_message

            message = moved_message(name)
            if message is not None:
                raise ModuleNotFoundError(message, name=name)
        return None


if not any(type(f).__name__ == "_MovedPaths" for f in sys.meta_path):
    sys.meta_path.append(_MovedPaths())



def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'smdm_plugin' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value  # resolve once
    return value


def __dir__() -> List[str]:
    """The public API only (``__all__``), not the helpers this module imports (``typing``, ...)."""
    return sorted(__all__)


if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs
    from .adapters.call import CallInputs
    from .adapters.checkpoint import load_checkpoint, save_sparse_config
    from .adapters.diffusion_wrapper import attach_diffusion, detach_diffusion
    from .adapters.families import FamilySpec, register_family
    from .adapters.family import ModelFamily
    from .adapters.inbetween_sampling import keyframe_constraint, sample_inbetween
    from .adapters.request import KeyframeRequest, with_forced
    from .adapters.state import sparse_config_of
    from .adapters.surgery import is_sparse, set_mean_std, sparsify, unsparsify
    from .adapters.text_cache import install_text_cache
    from .adapters.text_encoder import swap_text_encoder
    from .adapters.warm import warm_start, wrap_dense
    from .core.attention_backends import available_backends, register_backend
    from .core.config import SparseConfig
    from .core.presets import load_preset
    from .core.selection import register_selector, select_keyframes
    from .families.mdm.model import keyframe_collate
    from .io.bvh import load_cmu_clip, read_bvh
    from .metrics.evaluator import EvalResult, Evaluator, load_evaluator, score_motions
    from .reference.backbone import TinyMDM
    from .reference.simple_diffusion import SimpleDiffusion
    from .runtime.compile import CompileSetting, compile_model
    from .support.values import ConfigTypeError
    from .training.trainer import load_trained
