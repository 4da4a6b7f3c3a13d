"""smdm-plugin: sparse keyframe mode ("Less is More", sMDM) for MDM-family motion diffusion code.

Public API — everything users and the upstream patches/launcher rely on is importable from here.
"""
from .config import SparseConfig, load_preset
from .selection import select_keyframes, perturb_mask, vw_reference, keyframe_count
from .features import extract_selection_features
from .bvh import read_bvh, bvh_joint_positions, load_cmu_clip
from .interpolation import interpolate_keyframes
from .keyframe_transformer import KeyframeTransformer
from .attention_backends import register_backend, get_backend, available_backends
from .lipschitz import LipschitzMLP, lipschitz_loss, bake_lipschitz
from .fsq import FSQ, FSQMultiheadAttention, quantize_attention_keys
from .schedule import MaskSchedule
from .losses import dense_loss, keyframe_loss, lipschitz_term
from .backbone import TinyMDM
from .diffusion import SimpleDiffusion, ClassifierFreeGuidance
from .adapters.mdm import sparsify, unsparsify, is_sparse, detect_variant, set_mean_std
from .adapters.diffusion import attach_diffusion, detach_diffusion
from .checkpoint import save_sparse_config, load_checkpoint, check_state_dict, find_sparse_config

__version__ = "0.1.0"

__all__ = [
    "SparseConfig", "load_preset", "select_keyframes", "perturb_mask", "vw_reference", "keyframe_count",
    "read_bvh", "bvh_joint_positions", "load_cmu_clip",
    "extract_selection_features", "interpolate_keyframes", "KeyframeTransformer", "register_backend",
    "get_backend", "available_backends", "LipschitzMLP", "lipschitz_loss", "bake_lipschitz",
    "FSQ", "FSQMultiheadAttention", "quantize_attention_keys",
    "MaskSchedule", "dense_loss", "keyframe_loss", "lipschitz_term", "TinyMDM", "SimpleDiffusion",
    "ClassifierFreeGuidance", "sparsify", "unsparsify", "is_sparse", "detect_variant", "set_mean_std",
    "attach_diffusion", "detach_diffusion", "save_sparse_config", "load_checkpoint", "check_state_dict",
    "find_sparse_config", "__version__",
]
