"""Upstream MDM's ``MixedPrecisionTrainer._compute_norms`` (``diffusion/fp16_util.py``) as upstream
writes it: the reference the hooked norms are checked against."""
from __future__ import annotations

import numpy as np
import torch


class Trainer:
    """The part of upstream's ``MixedPrecisionTrainer`` the norms read: ``master_params``,
    ``use_fp16``, and its norms the way upstream computes them (a host sync per norm, summed in
    Python)."""

    def __init__(self, ps, use_fp16: bool = False):
        self.master_params, self.use_fp16 = ps, use_fp16

    def _compute_norms(self, grad_scale=1.0):
        grad_norm = param_norm = 0.0
        for p in self.master_params:
            with torch.no_grad():
                param_norm += torch.norm(p, p=2, dtype=torch.float32).item() ** 2
                if p.grad is not None:
                    grad_norm += torch.norm(p.grad, p=2, dtype=torch.float32).item() ** 2
        return np.sqrt(grad_norm) / grad_scale, np.sqrt(param_norm)
