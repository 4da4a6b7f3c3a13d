#!/usr/bin/env python
"""Build ``smdm_plugin/data/cmu_clips.npz``: a few CMU motion-capture clips embedded in the package
so that ``smdm demo`` runs with no download. Each clip is read from its BVH file with
:func:`smdm_plugin.io.bvh.load_cmu_clip` (HumanML3D's 22 joints, metres, 20 fps) and stored as
float32 ``[T, 22, 3]`` with its name and CMU description.

    python scripts/build_embedded_clips.py [--src ../shared/data/cmu-mocap] [--overwrite]

The data is from the CMU Graphics Lab Motion Capture Database (mocap.cs.cmu.edu), BVH conversion
by Bruce Hahne; CMU allows shipping it inside a product (not reselling it). Acknowledgment: "The
data used in this project was obtained from mocap.cs.cmu.edu. The database was created with
funding from NSF EIA-0196217."
"""
import argparse
import csv
import io
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from smdm_plugin.io.bvh import load_cmu_clip  # noqa: E402
from smdm_plugin.io.files import atomic_open, check_new_file  # noqa: E402

CLIPS = ("02_01", "02_03", "02_04", "02_05", "02_07", "05_02", "05_06", "06_02", "06_14", "07_12",
         "08_07", "35_17", "49_02", "49_04", "49_06", "49_18", "01_01")


def main() -> int:
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--src", default=os.path.join(os.path.dirname(here), "shared", "data", "cmu-mocap"))
    p.add_argument("--out", default=os.path.join(here, "smdm_plugin", "data", "cmu_clips.npz"))
    p.add_argument("--overwrite", action="store_true")
    a = p.parse_args()
    check_new_file(a.out, a.overwrite, "--out")
    with open(os.path.join(a.src, "clips.tsv")) as f:
        meta = {r["subject_trial"]: r for r in csv.DictReader(f, delimiter="\t")}
    arrays, names, descriptions = {}, [], []
    for clip in CLIPS:
        joints = load_cmu_clip(os.path.join(a.src, f"{clip}.bvh"), fps=20).astype(np.float32)
        arrays[f"clip_{clip}"] = joints
        names.append(clip)
        descriptions.append(meta[clip]["description"])
        print(f"{clip}: {len(joints)} frames ({meta[clip]['description']})")
    buf = io.BytesIO()
    np.savez_compressed(buf, names=np.array(names), descriptions=np.array(descriptions), **arrays)
    with atomic_open(a.out, "wb") as f:
        f.write(buf.getvalue())
    print(f"wrote {a.out} ({os.path.getsize(a.out) / 1024:.0f} KiB, {sum(len(v) for v in arrays.values())} frames)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
