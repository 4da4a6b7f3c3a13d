"""Motion capture embedded in the package: 17 CMU clips (walks, runs, jumps, dance, basketball,
cartwheel, ...) as HumanML3D-ordered joints, so that ``smdm demo`` runs with no download.

Each clip is ``[T, 22, 3]`` float32, metres, 20 fps, read from the CMU BVH files with
:func:`smdm_plugin.io.bvh.load_cmu_clip` by ``scripts/build_embedded_clips.py``. The data is from the
CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu), in Bruce Hahne's BVH conversion; see
``smdm_plugin/data/README.md`` for the terms and the acknowledgment CMU asks for.
"""
from __future__ import annotations

import os
from typing import List, Tuple

import numpy as np

PATH = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data", "cmu_clips.npz")
FPS = 20


def embedded_clips() -> List[Tuple[str, np.ndarray]]:
    """``[(name, joints [T, 22, 3] float32 metres at 20 fps)]``, in a fixed order."""
    with np.load(PATH) as z:
        return [(str(n), z[f"clip_{n}"]) for n in z["names"]]


def embedded_descriptions() -> dict:
    """CMU's description of every embedded clip, by name."""
    with np.load(PATH) as z:
        return {str(n): str(d) for n, d in zip(z["names"], z["descriptions"])}
