"""The pictures of docs/first_hour.md: frames of the GIFs that ``smdm render`` and ``smdm inbetween``
draw (the package's own renderer), saved as small PNGs.

    smdm demo --out WORK/demo                     # first (the tutorial's step 2)
    python scripts/make_first_hour_pictures.py --work WORK --bvh path/to/a/cmu_clip.bvh

Runs, in WORK: ``smdm clips export 05_02 --out dance.npy``, ``smdm render dance.npy``, ``smdm
inbetween --keyframes BVH --every 20`` with WORK/demo's models, then writes
docs/img/first_hour/*.png (one GIF frame each, 64-colour palette to keep them small).
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
from typing import List

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(ROOT, "docs", "img", "first_hour")


def smdm(work: str, *args: str) -> None:
    env = dict(os.environ, PYTHONPATH=ROOT)
    subprocess.run([sys.executable, "-m", "smdm_plugin", *args, *(["--overwrite"] if args[0] != "clips" else [])],
                   cwd=work, env=env, check=True)


def frames_to_png(gif: str, frames: List[int], name: str) -> None:
    from PIL import Image

    with Image.open(gif) as im:
        for f in frames:
            im.seek(f)
            path = os.path.join(OUT, f"{name}_frame{f:03d}.png")
            im.convert("RGB").quantize(colors=64).save(path, optimize=True)
            print(f"wrote {os.path.relpath(path, ROOT)} ({os.path.getsize(path) // 1024} KB)")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", required=True, help="folder holding demo/ (from smdm demo --out WORK/demo)")
    p.add_argument("--bvh", required=True, help="a CMU-skeleton BVH file standing for 'your own' clip")
    a = p.parse_args()
    os.makedirs(OUT, exist_ok=True)
    bvh = os.path.join(a.work, "my_clip.bvh")
    shutil.copyfile(a.bvh, bvh)
    if not os.path.exists(os.path.join(a.work, "dance.npy")):
        smdm(a.work, "clips", "export", "05_02", "--out", "dance.npy")
    smdm(a.work, "render", "dance.npy", "--keyframes", "0", "60", "120", "--out", "dance.gif", "--size", "2.5")
    frames_to_png(os.path.join(a.work, "dance.gif"), [60, 90], "render")
    smdm(a.work, "inbetween", "--model", "demo/dense", "demo/sparse", "--keyframes", "my_clip.bvh", "--every", "20",
         "--out", "ib", "--quiet")
    frames_to_png(os.path.join(a.work, "ib", "inbetween.gif"), [20, 30], "inbetween")


if __name__ == "__main__":
    main()
