"""Numbers as users pass them (core/scalars.py): numpy scalars and 0-d arrays are numbers wherever a
number is read (SparseConfig fields, selection, metrics), and a dict of fields is a config (sparsify's one
conversion, ``as_config``)."""
from __future__ import annotations

import numpy as np
import pytest

from smdm_plugin.adapters.surgery import as_config
from smdm_plugin.core.config import SparseConfig
from smdm_plugin.support.values import ConfigTypeError


# ------------------------------------------------------------------------------ numbers and configs
def test_numpy_scalars_are_numbers_and_dicts_are_configs():
    from smdm_plugin.core.selection import keyframe_count, select_keyframes  # noqa: F401

    c = SparseConfig(reduction=np.float32(0.8), gamma=np.float64(0.1), fsq=np.bool_(False),
                     diffusion_steps=np.int64(50), fsq_levels=np.array([8, 5]), mask_noise=np.array(0.1))
    assert c == SparseConfig(reduction=0.8, gamma=0.1, fsq=False, diffusion_steps=50, fsq_levels=(8, 5), mask_noise=0.1)
    assert type(c.reduction) is float and type(c.fsq) is bool and type(c.diffusion_steps) is int
    with pytest.raises(ConfigTypeError, match="reduction"):
        SparseConfig(reduction=np.complex64(0.5))
    with pytest.raises(ConfigTypeError, match="diffusion_steps"):
        SparseConfig(diffusion_steps=np.float32(50))
    # the one conversion of what users pass as a config (sparsify's)
    assert as_config({"reduction": 0.7}) == SparseConfig(reduction=0.7)
    assert as_config(c) == c and as_config(c) is not c and as_config(None) == SparseConfig()   # a checked copy
    with pytest.raises(ValueError, match=r"unknown option 'redution'; did you mean 'reduction'"):
        as_config({"redution": 0.7})
    with pytest.raises(TypeError, match=r"sparsify: config must be a SparseConfig, a dict of its fields or None"):
        as_config([("reduction", 0.7)])
    from smdm_plugin.core.selection import _check_reduction
    from smdm_plugin.metrics.quality import _fps

    assert _check_reduction(np.float32(0.8), "f") == 0.8 and _fps("f", np.float32(20)) == 20.0
