"""smdm-plugin: sparse keyframe mode ("Less is More", sMDM) for MDM-family motion diffusion code."""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any, Dict, List


__version__ = "0.8.0"

_EXPORTS: Dict[str, str] = {
    # core: the method
    "SparseConfig": "core.config", "load_preset": "core.presets", "sparse_config_of": "adapters.state",
    "select_keyframes": "core.selection", "register_selector": "core.selection", "perturb_mask": "core.selection",
    "vw_reference": "core.selection", "keyframe_count": "core.selection",
    "extract_selection_features": "core.features",
    "interpolate_keyframes": "core.interpolation",
    "KeyframeTransformer": "core.keyframe_transformer",
    "register_backend": "core.attention_backends", "get_backend": "core.attention_backends",
    "available_backends": "core.attention_backends",
    "LipschitzMLP": "core.lipschitz", "lipschitz_loss": "core.lipschitz", "bake_lipschitz": "core.lipschitz",
    "FSQ": "core.fsq", "FSQMultiheadAttention": "core.fsq", "quantize_attention_keys": "core.fsq",
    "unquantize_attention_keys": "core.fsq",
    "MaskSchedule": "core.schedule",
    "LaunchCounter": "core.launches", "LaunchCount": "core.launches", "count_launches": "core.launches",
    "dense_loss": "core.losses", "keyframe_loss": "core.losses", "lipschitz_term": "core.losses",
    # adapters: model surgery
    "sparsify": "adapters.surgery", "unsparsify": "adapters.surgery", "is_sparse": "adapters.surgery",
    "set_mean_std": "adapters.surgery", "detect_variant": "adapters.mdm",
    "wrap_dense": "adapters.warm", "warm_start": "adapters.warm", "is_dense_wrap": "adapters.warm",
    "ModelFamily": "adapters.family", "register_family": "adapters.families", "families": "adapters.families",
    "CallInputs": "adapters.call",
    "KeyframeRequest": "adapters.request", "KEYFRAMES_KEY": "adapters.request", "with_forced": "adapters.request",
    "attach_diffusion": "adapters.diffusion", "detach_diffusion": "adapters.diffusion",
    "keyframe_collate": "adapters.mdm",
    "swap_text_encoder": "adapters.text_encoder", "HFTextEncoder": "adapters.text_encoder",
    "install_text_cache": "adapters.text_cache", "TextEmbeddingCache": "adapters.text_cache",
    "ConfigTypeError": "core.values",
    # integrations: graph capture (--sparse_compile / smdm train --compile)
    "compile_model": "integrations.compile", "CompileSetting": "integrations.compile",
    "sample_inbetween": "adapters.inbetween", "keyframe_constraint": "adapters.inbetween",
    "forced_keyframes": "adapters.inbetween",
    # metrics
    "foot_skating_ratio": "metrics.quality", "jitter": "metrics.quality", "keyframe_error": "metrics.quality",
    "end_effector_speed": "metrics.motion", "to_joint_positions": "metrics.motion",
    "frechet_distance": "metrics.t2m", "diversity": "metrics.t2m", "multimodality": "metrics.t2m",
    "r_precision": "metrics.t2m", "matching_score": "metrics.t2m", "retrieval": "metrics.t2m",
    "Retrieval": "metrics.t2m", "mean_interval": "metrics.t2m",
    "Evaluator": "metrics.evaluator", "EvaluatorConfig": "metrics.evaluator", "load_evaluator": "metrics.evaluator",
    "save_evaluator": "metrics.evaluator", "score_motions": "metrics.evaluator", "EvalResult": "metrics.evaluator",
    "motion_quality": "metrics.evaluator",
    "jitter_per_speed": "metrics.quality", "mean_speed": "metrics.quality",
    # io
    "read_bvh": "io.bvh", "bvh_joint_positions": "io.bvh", "load_cmu_clip": "io.bvh",
    "BVHError": "io.bvh", "BVHWarning": "io.bvh", "OutputExistsError": "io.files",
    "save_sparse_config": "adapters.checkpoint", "load_checkpoint": "adapters.checkpoint",
    "check_state_dict": "io.checkpoint", "find_sparse_config": "io.checkpoint",
    # reference model
    "TinyMDM": "reference.backbone", "MotionDiffuseDenoiser": "reference.motiondiffuse_denoiser",
    "SimpleDiffusion": "reference.diffusion", "ClassifierFreeGuidance": "reference.diffusion",
    "TextConfig": "reference.text", "HashedBagOfWords": "reference.text", "sample_with_text": "reference.text",
}

__all__: List[str] = sorted(_EXPORTS) + ["__version__"]



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
    from .adapters.diffusion import attach_diffusion, detach_diffusion
    from .adapters.text_cache import TextEmbeddingCache, install_text_cache
    from .adapters.text_encoder import HFTextEncoder, swap_text_encoder
    from .adapters.call import CallInputs
    from .adapters.families import families, register_family
    from .adapters.family import ModelFamily
    from .adapters.request import KEYFRAMES_KEY, KeyframeRequest, with_forced
    from .adapters.mdm import detect_variant, keyframe_collate
    from .adapters.surgery import is_sparse, set_mean_std, sparsify, unsparsify
    from .adapters.warm import is_dense_wrap, warm_start, wrap_dense
    from .core.attention_backends import available_backends, get_backend, register_backend
    from .core.config import SparseConfig
    from .core.presets import load_preset
    from .core.values import ConfigTypeError
    from .adapters.state import sparse_config_of
    from .core.features import extract_selection_features
    from .core.fsq import FSQ, FSQMultiheadAttention, quantize_attention_keys, unquantize_attention_keys
    from .adapters.inbetween import forced_keyframes, keyframe_constraint, sample_inbetween
    from .metrics.motion import end_effector_speed, to_joint_positions
    from .metrics.quality import foot_skating_ratio, jitter, keyframe_error
    from .metrics.evaluator import (EvalResult, Evaluator, EvaluatorConfig, load_evaluator, motion_quality,
                                    save_evaluator, score_motions)
    from .metrics.t2m import (Retrieval, diversity, frechet_distance, matching_score, mean_interval, multimodality,
                              r_precision, retrieval)
    from .metrics.quality import jitter_per_speed, mean_speed
    from .core.interpolation import interpolate_keyframes
    from .core.keyframe_transformer import KeyframeTransformer
    from .core.lipschitz import LipschitzMLP, bake_lipschitz, lipschitz_loss
    from .core.losses import dense_loss, keyframe_loss, lipschitz_term
    from .core.schedule import MaskSchedule
    from .core.launches import LaunchCount, LaunchCounter, count_launches
    from .integrations.compile import CompileSetting, compile_model
    from .core.selection import register_selector
    from .core.selection import keyframe_count, perturb_mask, select_keyframes, vw_reference
    from .io.bvh import BVHError, BVHWarning, bvh_joint_positions, load_cmu_clip, read_bvh
    from .io.files import OutputExistsError
    from .adapters.checkpoint import load_checkpoint, save_sparse_config
    from .io.checkpoint import check_state_dict, find_sparse_config
    from .reference.backbone import TinyMDM
    from .reference.motiondiffuse_denoiser import MotionDiffuseDenoiser
    from .reference.diffusion import ClassifierFreeGuidance, SimpleDiffusion
    from .reference.text import HashedBagOfWords, TextConfig, sample_with_text
