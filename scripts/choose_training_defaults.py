#!/usr/bin/env python
"""Choose the training-time defaults (frame-index scale, mask noise, FSQ levels) by training.

For every variant of an ablation grid (``smdm ablate``'s YAML format; the grids written for this
are ``configs/ablations/frame_index_scale.yaml`` and ``training_defaults.yaml``) and
every seed, trains the in-package ``TinyMDM`` in sparse mode on the real HumanML3D-format clips
(same data order, timesteps and initial weights for every variant of a seed) and measures:

* ``val loss``: dense-frame denoising MSE on the held-out motions at fixed timesteps and noise,
  the model using its own sampling masks (``smdm_plugin.training.validation.validation_loss``);
* ``kf interp (mm)``: joint error of linearly interpolating the held-out motions from the keyframes
  the variant's selector picks (``smdm_plugin.metrics.feature_measures.keyframe_interpolation_error_mm``);
* of unconditional samples with the held-out motions' lengths: ``jitter`` (m/s³),
  ``foot skating`` (ratio) and ``EES`` (cm/frame) — :mod:`smdm_plugin.metrics` — next to the
  same numbers for the real held-out motions.

Writes ``<out>/<variant-slug>/seed<k>.json`` (a run whose file exists is not run again, so an
interrupted measurement resumes) and ``<out>/results.md`` (mean ± std over seeds, and per seed).
Single-threaded by default: on a shared CPU one thread per job is the fastest.

    python scripts/choose_training_defaults.py --grid frame_index_scale --seeds 0 1 2 --out results/fis
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any, Dict, List, Optional

import numpy as np
import torch

from smdm_plugin.apps.ablate import grid
from smdm_plugin.io.files import atomic_write_json, atomic_write_text
from smdm_plugin.metrics import end_effector_speed, to_joint_positions
from smdm_plugin.metrics.feature_measures import feature_quality, keyframe_interpolation_error_mm
from smdm_plugin.training.data import MotionData
from smdm_plugin.training.validation import validation_loss

METRICS = ("val_loss", "kf_interp_mm", "jitter", "foot_skating", "ees")
HEADERS = {"val_loss": "val loss", "kf_interp_mm": "kf interp (mm)", "jitter": "jitter (m/s³)",
           "foot_skating": "foot skating", "ees": "EES (cm/frame)"}
FORMATS = {"val_loss": ".4f", "kf_interp_mm": ".1f", "jitter": ".0f", "foot_skating": ".3f", "ees": ".2f"}


# ----------------------------------------------------------------------------------------- one run
def motion_quality(motion: torch.Tensor, lengths: torch.Tensor, data: MotionData,
                   fps: float = 20.0) -> Dict[str, float]:
    """Jitter, foot skating (as ``smdm ablate`` reports them) and EES of normalised HumanML3D
    features ``[B, N, 263]``."""
    joints = to_joint_positions(motion, data.mean, data.std).double()
    return {**feature_quality(motion, lengths, data.mean, data.std), "ees": float(end_effector_speed(joints, lengths))}


def train_and_measure(cfg: Dict[str, Any], variant: Dict[str, Any], data: MotionData,
                      seed: int, samples: int) -> Dict[str, Any]:
    """Train one variant with one seed (CPU) through the in-package Trainer, as ``smdm ablate``
    does, and return its measurements."""
    from smdm_plugin.training.trainer import TrainConfig, Trainer

    sc = grid.sparse_config(cfg, variant)
    tc = TrainConfig(steps=int(cfg["steps"]), batch=int(cfg["batch"]), lr=float(cfg["lr"]),
                     diffusion_steps=int(cfg["diffusion_steps"]), seed=seed, model=dict(cfg["model"]), sparse=sc)
    trainer = Trainer(tc, data.train, device="cpu")
    result = trainer.train()
    model, diffusion, losses, train_s = trainer.model, trainer.diffusion, result.losses, result.seconds
    model.eval()
    val_x, val_lengths = data.val.padded()
    lengths = val_lengths.repeat((samples + len(val_lengths) - 1) // len(val_lengths))[:samples]
    n = int(lengths.max())
    y = {"mask": (torch.arange(n) < lengths[:, None]).view(samples, 1, 1, n), "lengths": lengths}
    sample = diffusion.p_sample_loop(model, (samples, 263, 1, n), {"y": y},
                                     generator=torch.Generator().manual_seed(seed + 3))
    return {"variant": variant["name"], "seed": seed, "steps": int(cfg["steps"]),
            "final_loss": float(np.mean(losses[-max(1, len(losses) // 10):])),
            "val_loss": validation_loss(model, diffusion, data.val, torch.device("cpu"), seed),
            "kf_interp_mm": keyframe_interpolation_error_mm(val_x, val_lengths, data.val.joints, data.mean, data.std,
                                                            sc, seed=seed),
            **motion_quality(sample.squeeze(2).transpose(1, 2), lengths, data),
            "train_s": train_s, "sparse_config": None if sc is None else sc.to_dict()}


# ----------------------------------------------------------------------------------------- report
def _cell(values: List[Optional[float]], spec: str) -> str:
    vals = [v for v in values if v is not None]
    if not vals:
        return "—"
    if len(vals) == 1:
        return format(vals[0], spec)
    return f"{format(float(np.mean(vals)), spec)} ± {format(float(np.std(vals, ddof=1)), spec)}"


def report(cfg: Dict[str, Any], results: Dict[str, List[Dict[str, Any]]], real: Dict[str, float],
           seeds: List[int]) -> str:
    """Markdown: mean ± sample std over seeds per variant, then the per-seed values."""
    lines = [f"{cfg.get('name', 'grid')}: TinyMDM {cfg['model']}, {cfg['steps']} steps × batch {cfg['batch']}, "
             f"{cfg['diffusion_steps']} diffusion steps, sparse base {cfg.get('sparse')}; seeds {seeds}; "
             f"{torch.get_num_threads()} thread(s)", "",
             "| variant | " + " | ".join(HEADERS[m] for m in METRICS) + " |",
             "| --- |" + " ---: |" * len(METRICS)]
    for name, runs in results.items():
        lines.append(f"| {name} | " + " | ".join(_cell([r.get(m) for r in runs], FORMATS[m]) for m in METRICS) + " |")
    lines.append("| real held-out motions | — | — | " + " | ".join(
        format(real[m], FORMATS[m]) for m in ("jitter", "foot_skating", "ees")) + " |")
    lines += ["", "Per seed (val loss / jitter / foot skating):", "",
              "| variant | " + " | ".join(f"seed {s}" for s in seeds) + " |", "| --- |" + " --- |" * len(seeds)]
    for name, runs in results.items():
        by_seed = {r["seed"]: r for r in runs}
        lines.append(f"| {name} | " + " | ".join(
            f"{by_seed[s]['val_loss']:.4f} / {by_seed[s]['jitter']:.0f} / {by_seed[s]['foot_skating']:.3f}"
            if s in by_seed else "—" for s in seeds) + " |")
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------------- CLI
def main(argv: Optional[List[str]] = None) -> int:
    from smdm_plugin.apps.common.args import add_overwrite, int_range

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--grid", required=True, help="ablation grid: a YAML path or a packaged grid name")
    p.add_argument("--out", required=True, help="results folder (resumed when it holds this grid's runs)")
    p.add_argument("--seeds", type=int_range(0), nargs="+", default=[0, 1])
    p.add_argument("--samples", type=int_range(1), default=16, help="generated motions per run")
    p.add_argument("--steps", type=int_range(1), default=None, help="override the grid's optimiser steps")
    p.add_argument("--only", nargs="+", default=None, help="run only these variants (names or slugs)")
    p.add_argument("--data", default=None, help=f"HumanML3D-format folder (default {grid.DEFAULT_DATA})")
    p.add_argument("--threads", type=int_range(1), default=1)
    add_overwrite(p)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    try:
        cfg = grid.load_config(a.grid)
    except (FileNotFoundError, ValueError) as e:
        p.error(str(e))
    if a.steps:
        cfg["steps"] = a.steps
    data_root = a.data or cfg.get("data") or grid.DEFAULT_DATA
    if not os.path.exists(os.path.join(data_root, "Mean.npy")):
        p.error(f"--data {data_root!r} holds no HumanML3D-format data (Mean.npy, new_joint_vecs/, train.txt)")
    stamp = {"grid": {k: v for k, v in cfg.items() if k != "data"}, "samples": a.samples}
    stamp_path = os.path.join(a.out, "grid.json")
    if os.path.exists(stamp_path) and not a.overwrite:
        with open(stamp_path) as f:
            if json.load(f) != json.loads(json.dumps(stamp)):
                p.error(f"--out {a.out!r} holds runs of another grid or settings; pass --overwrite or another --out")
    os.makedirs(a.out, exist_ok=True)
    atomic_write_json(stamp_path, stamp, indent=2)
    data = MotionData(data_root, int(cfg["max_frames"]))
    real = motion_quality(*data.val.padded(), data)
    results: Dict[str, List[Dict[str, Any]]] = {}
    for variant in cfg["variants"]:
        if a.only and variant["name"] not in a.only and grid.slug(variant["name"]) not in a.only:
            continue
        runs = results.setdefault(variant["name"], [])
        for seed in a.seeds:
            path = os.path.join(a.out, grid.slug(variant["name"]), f"seed{seed}.json")
            if os.path.exists(path) and not a.overwrite:
                with open(path) as f:
                    runs.append(json.load(f))
                continue
            os.makedirs(os.path.dirname(path), exist_ok=True)
            res = train_and_measure(cfg, variant, data, seed, a.samples)
            atomic_write_json(path, res, indent=2)
            runs.append(res)
            print(f"{variant['name']} seed {seed}: val {res['val_loss']:.4f}, jitter {res['jitter']:.0f}, "
                  f"skating {res['foot_skating']:.3f}, {res['train_s']:.0f} s", flush=True)
    text = report(cfg, results, real, a.seeds)
    atomic_write_text(os.path.join(a.out, "results.md"), text)
    print("\n" + text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
