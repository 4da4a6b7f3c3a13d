"""Motion quality metrics on joint positions (metres) or HumanML3D features.

* :mod:`.motion` — End-Effector Speed (EES) and the conversion of features to joint positions;
* :mod:`.quality` — foot skating ratio, jitter (mean jerk) and keyframe error, as the keyframe
  in-betweening literature (GMD, CondMDI, DNO) computes them;
* :mod:`.inbetween` — in-betweening: transitions between given and generated frames, and one
  dict of keyframe error, jitter (overall, at the transitions) and foot skating (from :mod:`.quality`);
* :mod:`.doubletake` — the motion/transition split of DoubleTake's long sequences.
"""
from ..io.humanml3d import recover_from_ric, recover_root
from .doubletake import doubletake_ees, motion_transition_masks, unfolded_step_sizes
from .motion import (HUMANML3D_END_EFFECTORS, KIT_END_EFFECTORS, end_effector_speed,
                     to_joint_positions)
from .inbetween import keyframe_metrics, transition_frames
from .quality import HUMANML3D_FEET, foot_skating_ratio, jitter, keyframe_error
from .quality import jitter_per_speed, mean_speed

__all__ = ["HUMANML3D_END_EFFECTORS", "KIT_END_EFFECTORS", "HUMANML3D_FEET", "end_effector_speed",
           "foot_skating_ratio", "jitter", "keyframe_error", "keyframe_metrics", "transition_frames", "to_joint_positions",
           "recover_from_ric", "recover_root", "doubletake_ees", "motion_transition_masks",
           "unfolded_step_sizes", "jitter_per_speed", "mean_speed"]
