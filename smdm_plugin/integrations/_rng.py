"""Keep upstream's random streams where they were: the plugin's own draws outside the model (the
sparse layers' initial weights drawn when a model is sparsified) must not shift the prompts, noise
or batches that upstream draws next from the same seed.

:func:`upstream_rng_untouched` saves the global ``torch`` (CPU and every initialised CUDA device),
``numpy`` and ``random`` states and puts them back on exit, so a run with ``--sparse`` draws the
same upstream stream as one without it. What the plugin draws inside the block is still a function
of the user's seed (it starts from the same state), so runs stay reproducible.
"""
from __future__ import annotations

import contextlib
import random
from typing import Iterator

import torch


@contextlib.contextmanager
def upstream_rng_untouched() -> Iterator[None]:
    """Run the block, then restore the global ``torch``/CUDA/``numpy``/``random`` RNG states."""
    import numpy as np

    py_state = random.getstate()
    np_state = np.random.get_state()
    cuda = torch.cuda.is_available() and torch.cuda.is_initialized()
    devices = list(range(torch.cuda.device_count())) if cuda else []
    with torch.random.fork_rng(devices=devices):
        try:
            yield
        finally:
            random.setstate(py_state)
            np.random.set_state(np_state)
