"""The tensors of a keyframe plan as the plan op returns them (its composite and its Triton kernel
alike): one type, imported by both."""
from __future__ import annotations

from typing import Tuple

import torch

Tensor = torch.Tensor
#: ``(slot frame index, slot valid, frame slot, ...)``: what ``keyframe_plan`` returns (see plan_op)
Plan = Tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]
