#!/usr/bin/env python
"""Keyframe reconstruction error of the selectors on real CMU motion, to choose defaults.

For every motion, keyframes are selected from 64-D features (21 root-relative joints + frame
index × frame_index_scale) and all 22 joints' positions are linearly interpolated between them;
the error is the mean per-joint position error (mm) over all valid frames (pooled over motions).
Also reported: the largest gap between consecutive keyframes (frames, max over motions) and its
mean over motions.

Data sets (../shared/data): ``hml`` = cmu-humanml3d (features from new_joint_vecs through
``extract_selection_features`` with Mean/Std, positions from new_joints); ``bvh`` = the same
79 segments straight from the BVH files (``load_cmu_clip``, features ``extract_selection_features(..., 'joints')``,
world positions). Usage:
``python scripts/choose_selection_defaults.py [--bench] [--root-relative] [--quality]``
(``--quality``: jitter, foot skating and EES of the motions rebuilt from the keyframes).
"""
from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path
from typing import Dict, List, Tuple

import numpy as np
import torch

from smdm_plugin.io.bvh import load_cmu_clip
from smdm_plugin.core.selection_features import extract_selection_features
from smdm_plugin.core.selection import select_keyframes
from smdm_plugin.metrics import end_effector_speed, foot_skating_ratio, jitter

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SCALES = (0.0, 0.001, 0.003, 0.01, 0.03, 0.1)
EXTRA_SCALES = (0.3, 1.0, 3.0, 10.0)  # beyond the first grid: where the error levels off
REDUCTIONS = (0.6, 0.7, 0.8, 0.9)
RANDOM_SEEDS = (0, 1, 2)


def load_hml() -> Tuple[np.ndarray, np.ndarray, List[int], np.ndarray, np.ndarray]:
    """Normalised vectors [B, N, 263], positions [B, N, 22, 3], lengths, mean, std."""
    root = DATA / "cmu-humanml3d"
    mean, std = np.load(root / "Mean.npy"), np.load(root / "Std.npy")
    ids = (root / "all.txt").read_text().split()
    vecs = [np.load(root / "new_joint_vecs" / f"{i}.npy") for i in ids]
    pos = [np.load(root / "new_joints" / f"{i}.npy") for i in ids]
    N = max(len(v) for v in vecs)
    x = np.zeros((len(ids), N, 263), np.float32)
    P = np.zeros((len(ids), N, 22, 3))
    for b, (v, p) in enumerate(zip(vecs, pos)):
        x[b, :len(v)] = (v - mean) / std
        P[b, :len(v)] = p
    return x, P, [len(v) for v in vecs], mean, std


def load_bvh_segments() -> Tuple[np.ndarray, List[int]]:
    """World positions [B, N, 22, 3] (metres) of the index.csv segments, and lengths."""
    clips: Dict[str, np.ndarray] = {}
    segs = []
    for r in csv.DictReader(open(DATA / "cmu-humanml3d" / "index.csv")):
        if r["clip"] not in clips:
            clips[r["clip"]] = load_cmu_clip(DATA / "cmu-mocap" / f"{r['clip']}.bvh")
        a, b = (int(r["first_file_frame"]) - 1) // 6, (int(r["last_file_frame"]) - 1) // 6
        segs.append(clips[r["clip"]][a:b + 1])
    N = max(len(s) for s in segs)
    P = np.zeros((len(segs), N, 22, 3))
    for b, s in enumerate(segs):
        P[b, :len(s)] = s
    return P, [len(s) for s in segs]


def reconstruct(P: np.ndarray, lengths: List[int], mask: np.ndarray) -> np.ndarray:
    """Joints ``[B, N, 22, 3]`` linearly interpolated from the keyframes (valid frames only)."""
    rec = np.zeros_like(P)
    for b, L in enumerate(lengths):
        k = np.flatnonzero(mask[b, :L])
        flat = P[b, :L].reshape(L, -1)
        rec[b, :L] = np.stack([np.interp(np.arange(L), k, flat[k, c]) for c in range(flat.shape[1])],
                              1).reshape(L, 22, 3)
    return rec


def interp_error(P: np.ndarray, lengths: List[int], mask: np.ndarray) -> Tuple[float, int, float]:
    """(MPJPE mm over valid frames, max keyframe gap, mean per-motion max gap)."""
    rec = reconstruct(P, lengths, mask)
    valid = np.arange(P.shape[1])[None] < np.asarray(lengths)[:, None]
    err = np.linalg.norm(rec - P, axis=-1).mean(-1)[valid]
    gaps = [int(np.diff(np.flatnonzero(mask[b, :L])).max()) for b, L in enumerate(lengths)]
    return 1000.0 * float(err.mean()), max(gaps), float(np.mean(gaps))


def quality_table(name: str, feats_for_scale, P: np.ndarray, lengths: List[int], reduction: float = 0.8) -> None:
    """Jitter and foot skating of the motions rebuilt from the keyframes (global positions):
    what a perfect sparse model, which gets the keyframes right and interpolates, would output."""
    lens_t = torch.tensor(lengths)
    kw = {"fps": 20.0, "lengths": lens_t}
    rows = [("real motion", P)]
    for s in SCALES + EXTRA_SCALES:
        mask = select_keyframes(feats_for_scale(s), lens_t, reduction, "vw").numpy()
        rows.append((f"vw, scale {s:g}", reconstruct(P, lengths, mask)))
    mask = select_keyframes(feats_for_scale(0.0), lens_t, reduction, "uniform").numpy()
    rows.append(("uniform", reconstruct(P, lengths, mask)))
    print(f"\n### {name}: motion rebuilt from {100 * (1 - reduction):.0f}% keyframes\n")
    print("| keyframes | jitter (m/s³) | foot skating ratio | EES (cm/frame) |")
    print("| --- | ---: | ---: | ---: |")
    for label, Q in rows:
        print(f"| {label} | {float(jitter(Q, **kw)):.1f} | {float(foot_skating_ratio(Q, **kw)):.4f} | "
              f"{float(end_effector_speed(torch.from_numpy(Q), lens_t)):.3f} |")


def evaluate(name: str, feats_for_scale, P: np.ndarray, lengths: List[int]) -> None:
    """Print the Markdown table for one data set; ``feats_for_scale(s) -> [B, N, 64]``."""
    lens_t = torch.tensor(lengths)
    rows: List[Tuple[str, List[Tuple[float, int, float]]]] = []
    for s in SCALES + EXTRA_SCALES:
        f = feats_for_scale(s)
        tag = " (extra)" if s in EXTRA_SCALES else ""
        rows.append((f"vw, scale {s:g}{tag}", [interp_error(
            P, lengths, select_keyframes(f, lens_t, r, "vw").numpy()) for r in REDUCTIONS]))
    f = feats_for_scale(0.01)
    rows.append(("uniform", [interp_error(P, lengths, select_keyframes(
        f, lens_t, r, "uniform").numpy()) for r in REDUCTIONS]))
    res = []
    for r in REDUCTIONS:
        per_seed = [interp_error(P, lengths, select_keyframes(
            f, lens_t, r, "random", torch.Generator().manual_seed(seed)).numpy())
            for seed in RANDOM_SEEDS]
        res.append((float(np.mean([p[0] for p in per_seed])), max(p[1] for p in per_seed),
                    float(np.mean([p[2] for p in per_seed]))))
    rows.append((f"random (mean of {len(RANDOM_SEEDS)} seeds)", res))
    for s in (0.0, 0.01):
        f = feats_for_scale(s)
        rows.append((f"mdo, scale {s:g}", [interp_error(P, lengths, select_keyframes(
            f, lens_t, r, "mdo").numpy()) for r in REDUCTIONS]))
    print(f"\n### {name}: {len(lengths)} motions, {sum(lengths)} frames\n")
    print("MPJPE of linear interpolation from the keyframes, mm (max gap / mean per-motion "
          "max gap, frames)\n")
    print("| selector | " + " | ".join(f"reduction {r}" for r in REDUCTIONS) + " |")
    print("| --- |" + " --- |" * len(REDUCTIONS))
    for label, vals in rows:
        print(f"| {label} | " + " | ".join(f"{e:.1f} ({g} / {mg:.1f})" for e, g, mg in vals)
              + " |")


def bench() -> None:
    x = torch.randn(64, 196, 64).cumsum(1)
    times = []
    for _ in range(30):
        t = time.perf_counter()
        select_keyframes(x, None, 0.8)
        times.append(time.perf_counter() - t)
    print(f"select_keyframes [64, 196, 64], reduction 0.8, vw: median "
          f"{1000 * np.median(times):.1f} ms, min {1000 * np.min(times):.1f} ms "
          f"({torch.get_num_threads()} threads)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bench", action="store_true", help="also time select_keyframes")
    ap.add_argument("--root-relative", action="store_true",
                    help="measure the error on root-relative positions (pose only)")
    ap.add_argument("--quality", action="store_true",
                    help="also the jitter / foot skating / EES of the motions rebuilt from the keyframes")
    args = ap.parse_args()
    rel = (lambda q: q - q[:, :, :1]) if args.root_relative else (lambda q: q)
    what = "root-relative positions" if args.root_relative else "global positions"
    if not (DATA / "cmu-humanml3d" / "Mean.npy").exists():
        raise SystemExit(f"needs {DATA}/cmu-humanml3d and {DATA}/cmu-mocap")
    x, P, lengths, mean, std = load_hml()
    evaluate(f"cmu-humanml3d (263-D vectors -> 64-D features), error on {what}",
             lambda s: extract_selection_features(torch.from_numpy(x), "humanml3d", mean, std, s),
             rel(P), lengths)
    Pb, lb = load_bvh_segments()
    evaluate(f"cmu-mocap BVH (world joints -> root-relative 64-D features), error on {what}",
             lambda s: extract_selection_features(torch.from_numpy(np.asarray(Pb, np.float64).reshape(*Pb.shape[:2], 66)),
                                                 "joints", frame_index_scale=s), rel(Pb), lb)
    if args.quality:
        quality_table("cmu-humanml3d, global positions",
                      lambda s: extract_selection_features(torch.from_numpy(x), "humanml3d", mean, std, s), P, lengths)
    if args.bench:
        bench()


if __name__ == "__main__":
    main()
