"""Jitter per unit speed and foot skating of sparse sampling variants, against dense and real motion.

Trains the in-package backbone (TinyMDM + SimpleDiffusion) dense and sparse (80% dropped, VW) for the
same number of steps from the same weights, for each seed, then samples ``--samples`` unconditional
motions from each with the same noise and scores them (:mod:`smdm_plugin.metrics`, 20 fps):
jitter (m/s³), mean joint speed (m/s), jitter per unit speed ("j/s", 1/s²: jitter over speed, the
ratio of the set's means) and the foot skating ratio. The sparse model is sampled with every
sampling variant of :data:`VARIANTS` (``SparseConfig`` sampling options: no retraining). Prints a
markdown table (mean ± 95% t-interval over seeds) and writes it to ``--out`` when given.

    python scripts/measure_smooth_sampling.py                      # the embedded CMU clips (joints66)
    python scripts/measure_smooth_sampling.py --data ../shared/data/cmu-humanml3d   # HumanML3D 263-D

Bounded: with the defaults about 10 minutes on one idle CPU thread (37 on a loaded 2-core machine).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from typing import Callable, Dict, List, Tuple

import numpy as np
import torch

from smdm_plugin import SparseConfig
from smdm_plugin.support.argtypes import int_range
from smdm_plugin.adapters.state import get_state
from smdm_plugin.core.schedule import MaskSchedule
from smdm_plugin.metrics import foot_skating_ratio, jitter, mean_speed

#: sampling variants of the sparse model: name -> SparseConfig changes
VARIANTS: Dict[str, Dict] = {
    "linear, dynamic on (paper at T >= 100)": dict(sample_interpolation="linear", dynamic_update=True),
    "linear, dynamic off (paper at T < 100)": dict(sample_interpolation="linear", dynamic_update=False),
    "cubic last step, dynamic on": dict(sample_interpolation="cubic", sample_interpolation_steps=1,
                                        dynamic_update=True),
    "cubic, dynamic on": dict(sample_interpolation="cubic", sample_interpolation_steps=None, dynamic_update=True),
    # with a fixed (uniform) mask the non-keyframe outputs never feed back (only keyframe tokens enter
    # the model), so cubic in the last step only or in every step give the same samples
    "cubic, dynamic off": dict(sample_interpolation="cubic", sample_interpolation_steps=None,
                               dynamic_update=False),
    # the package default: auto = linear for HumanML3D/KIT features, cubic for raw joint positions
    "defaults (auto fill, dynamic off)": dict(sample_interpolation="auto", sample_interpolation_steps=None,
                                              dynamic_update=False),
}
T95 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262}


def load_data(data: str, frames: int):
    """``(MotionSet for training, real joints [M, frames, 22, 3], to_joints(normalised x [B, N, D]))``."""
    from smdm_plugin.io.humanml3d import load_humanml3d
    from smdm_plugin.training.data import MotionSet, feature_stats

    if data == "embedded":
        from smdm_plugin.apps.demo import motion_features, training_crops
        from smdm_plugin.io.embedded import embedded_clips
        from smdm_plugin.io.representation import Representation

        clips = [c for c in embedded_clips() if len(c[1]) >= frames]
        held, train = clips[-1], clips[:-1]
        crops = training_crops(train, frames, stride=max(1, frames // 8))
        feats = [motion_features(c) for c in crops]
        mean, std = feature_stats(feats)
        rep = Representation("joints66")
        real = np.stack(training_crops([held] + train, frames, stride=frames))
        to_joints = lambda x: torch.as_tensor(rep.to_joints(x * torch.from_numpy(std) + torch.from_numpy(mean)))
        return MotionSet.from_motions(feats, mean, std, max_frames=frames), real, to_joints
    from smdm_plugin.metrics import to_joint_positions

    train = MotionSet.from_split(load_humanml3d(data, "train", max_frames=frames, min_frames=min(40, frames)))
    test = MotionSet.from_split(load_humanml3d(data, "test", max_frames=frames, min_frames=frames))
    to_joints = lambda x: to_joint_positions(x.float(), train.mean, train.std)
    xr, _ = test.padded()
    real = to_joints(xr * torch.from_numpy(test.std) / torch.from_numpy(train.std)
                     + (torch.from_numpy(test.mean) - torch.from_numpy(train.mean)) / torch.from_numpy(train.std))
    return train, real.numpy(), to_joints


def scores(j: torch.Tensor) -> Dict[str, float]:
    jit = float(jitter(j, fps=20))
    spd = float(mean_speed(j, fps=20))
    return {"jitter": jit, "speed": spd, "jps": jit / spd, "skating": float(foot_skating_ratio(j, fps=20))}


def sample(model, diffusion, n: int, N: int, D: int, seed: int) -> torch.Tensor:
    y = {"mask": torch.ones(n, 1, 1, N, dtype=torch.bool), "lengths": torch.full((n,), N, dtype=torch.long)}
    g = torch.Generator().manual_seed(seed + 11)
    x = diffusion.p_sample_loop(model, (n, D, 1, N), {"y": y}, generator=g)
    return x.squeeze(2).permute(0, 2, 1).float()


def set_sampling(model, mean, std, **changes) -> None:
    """Re-point a trained sparse model's sampling schedule at ``changes`` (sampling options only)."""
    state = get_state(model)
    config = state.config.replace(**changes)
    state.config = config
    state.schedule = MaskSchedule(config, mean, std)


def interval(values: List[float]) -> Tuple[float, float]:
    v = np.asarray(values, np.float64)
    if len(v) < 2:
        return float(v.mean()), float("nan")
    return float(v.mean()), float(T95.get(len(v) - 1, 1.96) * v.std(ddof=1) / math.sqrt(len(v)))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default="embedded", help="'embedded' (the package's CMU clips) or a HumanML3D folder")
    p.add_argument("--seeds", type=int_range(1), default=3)
    p.add_argument("--steps", type=int_range(1), default=400, help="training steps, each model")
    p.add_argument("--sparse-steps", type=int_range(1), default=None,
                   help="training steps of the sparse model (default: --steps, equal steps; more: equal time)")
    p.add_argument("--no-dense", action="store_true", help="score the sparse model only")
    p.add_argument("--samples", type=int_range(2), default=32)
    p.add_argument("--frames", type=int_range(20), default=120)
    p.add_argument("--latent", type=int_range(4), default=128)
    p.add_argument("--layers", type=int_range(1), default=2)
    p.add_argument("--batch", type=int_range(1), default=32)
    p.add_argument("--diffusion-steps", type=int_range(1), default=50, help="T (the paper's: 50)")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS), metavar="NAME")
    p.add_argument("--threads", type=int_range(1), default=1)
    p.add_argument("--out", default=None, help="write the markdown table (and a .json beside it) here")
    p.add_argument("--overwrite", action="store_true")
    args = p.parse_args(argv)
    if args.out and os.path.exists(args.out) and not args.overwrite:
        p.error(f"argument --out: {args.out!r} exists; pass --overwrite to replace it")
    if args.data != "embedded" and not os.path.isdir(args.data):
        p.error(f"argument --data: {args.data!r} is not a folder (or 'embedded')")
    torch.set_num_threads(args.threads)
    from smdm_plugin.training.trainer import TrainConfig, Trainer

    data, real, to_joints = load_data(args.data, args.frames)
    N, D = args.frames, data.feature_dim
    rows: Dict[str, List[Dict[str, float]]] = {}
    t0 = time.perf_counter()
    model_args = {"latent_dim": args.latent, "ff_size": 2 * args.latent, "num_layers": args.layers,
                  "num_heads": 4, "dropout": 0.1}
    sparse_cfg = SparseConfig(reduction=0.8, feature="raw" if D == 66 else "auto")
    for seed in range(args.seeds):
        for name, sc in (("dense", None), ("sparse", sparse_cfg))[int(args.no_dense):]:
            steps = args.steps if sc is None else (args.sparse_steps or args.steps)
            tr = Trainer(TrainConfig(steps=steps, batch=args.batch, diffusion_steps=args.diffusion_steps,
                                     seed=seed, model=model_args, sparse=sc), data, device="cpu")
            tr.train()
            model = tr.model.eval()
            todo = {"dense": {}} if sc is None else {f"sparse: {v}": VARIANTS[v] for v in args.variants}
            for label, changes in todo.items():
                if changes:
                    set_sampling(model, data.mean, data.std, **changes)
                x = sample(model, tr.diffusion, args.samples, N, D, seed)
                rows.setdefault(label, []).append(scores(to_joints(x)))
                print(f"seed {seed} {label}: {rows[label][-1]}  ({time.perf_counter() - t0:.0f} s)", flush=True)
    real_s = scores(torch.as_tensor(real))
    lines = [f"data: {args.data}; {args.seeds} seeds x {args.samples} samples of {N} frames; TinyMDM latent "
             f"{args.latent}, {args.layers} layers, batch {args.batch}, {args.steps} steps dense, "
             f"{args.sparse_steps or args.steps} sparse, T = "
             f"{args.diffusion_steps}; 80% dropped (VW). Mean ± 95% interval over seeds.", "",
             "| motion | j/s (1/s²) | jitter (m/s³) | speed (m/s) | foot skating |",
             "| --- | ---: | ---: | ---: | ---: |"]
    for label, rs in rows.items():
        cells = []
        for k, fmt in (("jps", "{:.0f} ± {:.0f}"), ("jitter", "{:.0f} ± {:.0f}"), ("speed", "{:.2f} ± {:.2f}"),
                       ("skating", "{:.3f} ± {:.3f}")):
            cells.append(fmt.format(*interval([r[k] for r in rs])))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append(f"| real motion ({len(real)} windows) | {real_s['jps']:.0f} | {real_s['jitter']:.0f} | "
                 f"{real_s['speed']:.2f} | {real_s['skating']:.3f} |")
    table = "\n".join(lines)
    print(table)
    if args.out:
        from smdm_plugin.io.files import atomic_write_json, atomic_write_text

        atomic_write_text(args.out, table + "\n")
        atomic_write_json(os.path.splitext(args.out)[0] + ".json",
                          {"args": vars(args), "rows": rows, "real": real_s}, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
