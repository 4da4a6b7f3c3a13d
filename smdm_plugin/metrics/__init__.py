"""Motion quality metrics on joint positions (metres) or HumanML3D features.

* :mod:`.motion` — End-Effector Speed (EES) and the conversion of features to joint positions;
* :mod:`.doubletake` — the motion/transition split of DoubleTake's long sequences.
"""
from ..io.humanml3d import recover_from_ric, recover_root
from .doubletake import doubletake_ees, motion_transition_masks, unfolded_step_sizes
from .motion import (HUMANML3D_END_EFFECTORS, KIT_END_EFFECTORS, end_effector_speed,
                     to_joint_positions)

__all__ = ["HUMANML3D_END_EFFECTORS", "KIT_END_EFFECTORS", "end_effector_speed", "to_joint_positions",
           "recover_from_ric", "recover_root", "doubletake_ees", "motion_transition_masks",
           "unfolded_step_sizes"]
