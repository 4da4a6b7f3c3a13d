"""Motion quality metrics on joint positions (metres) or HumanML3D features.

* :mod:`.motion` — End-Effector Speed (EES) and the conversion of features to joint positions;
* :mod:`.quality` — foot skating ratio, jitter (mean jerk) and keyframe error, as the keyframe
  in-betweening literature (GMD, CondMDI, DNO) computes them;
* :mod:`.inbetween` — in-betweening: transitions between given and generated frames, and one
  dict of keyframe error, jitter (overall, at the transitions) and foot skating (from :mod:`.quality`);
* :mod:`.doubletake` — the motion/transition split of DoubleTake's long sequences;
* :mod:`.t2m` — the text-to-motion metrics of Guo et al. 2022 on evaluator embeddings: FID,
  diversity, multimodality, R-precision and matching score (T2M's protocol).
"""
from ..io.humanml3d import recover_from_ric, recover_root
from .doubletake import doubletake_ees, motion_transition_masks, unfolded_step_sizes
from .motion import (HUMANML3D_END_EFFECTORS, KIT_END_EFFECTORS, end_effector_speed,
                     to_joint_positions)
from .inbetween_metrics import keyframe_metrics, transition_frames
from .quality import HUMANML3D_FEET, foot_skating_ratio, jitter, keyframe_error
from .t2m import (Retrieval, diversity, frechet_distance, matching_score, mean_interval, multimodality,
                  r_precision, retrieval)
from .quality import jitter_per_speed, mean_speed

__all__ = ["HUMANML3D_END_EFFECTORS", "KIT_END_EFFECTORS", "HUMANML3D_FEET", "end_effector_speed",
           "foot_skating_ratio", "jitter", "keyframe_error", "keyframe_metrics", "transition_frames", "to_joint_positions",
           "recover_from_ric", "recover_root", "doubletake_ees", "motion_transition_masks",
           "unfolded_step_sizes", "Retrieval", "diversity", "frechet_distance", "matching_score", "mean_interval",
           "multimodality", "r_precision", "retrieval", "jitter_per_speed", "mean_speed"]
