"""The motion metrics on positions so large that float32 overflows: a warning that says so (positions are
expected in metres), never a silent inf / NaN in a table."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from smdm_plugin.metrics.quality import MetricOverflowWarning, jitter, jitter_per_speed, mean_speed


# ------------------------------------------------------------------------------ metrics
def test_metrics_warn_when_finite_positions_overflow():
    """0.4.0: jitter and j/s of a 1e30 motion were inf / NaN ("—" in the tables) without a word."""
    a = np.random.default_rng(0).random((30, 22, 3)).astype(np.float32)
    a[5] = 1e30
    for fn in (jitter, mean_speed, jitter_per_speed):
        with pytest.warns(MetricOverflowWarning, match="overflowed .* reaching 1e\\+30; positions are expected in "
                                                        "metres"):
            v = fn(a)
        assert not torch.isfinite(v)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a normal motion: no warning
        assert torch.isfinite(jitter(a[:5])) and torch.isfinite(jitter(np.where(np.abs(a) > 1, 0, a)))
