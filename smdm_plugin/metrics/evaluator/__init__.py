"""The T2M text-to-motion evaluator (Guo et al. 2022): networks with the published checkpoint's
layout, caption reading, loading either layout, scoring motions, training one on your own data,
the evaluation protocol's draws and the sensitivity table (what an evaluator can resolve)."""
from .check import SensitivityTable, load_check, save_check, sensitivity
from .model import (Evaluator, EvaluatorConfig, evaluator_info, evaluator_layout, load_evaluator,
                    load_upstream_evaluator, save_evaluator)
from .networks import MotionEncoderBiGRUCo, MovementConvDecoder, MovementConvEncoder, TextEncoderBiGRUCo
from .protocol import PROTOCOLS, Replication, replication
from .score import EvalResult, embed_captions, embed_motions, motion_quality, score_embeddings, score_motions

__all__ = ["Evaluator", "EvaluatorConfig", "load_evaluator", "load_upstream_evaluator", "save_evaluator",
           "evaluator_layout", "evaluator_info", "MovementConvEncoder", "MotionEncoderBiGRUCo", "TextEncoderBiGRUCo",
           "EvalResult", "score_motions", "score_embeddings", "embed_motions", "embed_captions", "motion_quality",
           "MovementConvDecoder", "SensitivityTable", "sensitivity", "save_check", "load_check", "PROTOCOLS",
           "Replication", "replication"]
