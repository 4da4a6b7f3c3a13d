#!/usr/bin/env python
"""Rough sweep to pick ``SparseConfig.sine_w0`` and ``SparseConfig.lipschitz_lambda``.

On real HumanML3D-format motion (``--data``, default ``../shared/data/cmu-humanml3d`` beside the repository: 263-D features, normalised
with its ``Mean.npy``/``Std.npy``), trains a per-frame auto-encoder made of sMDM's two Lipschitz
layers, ``LipschitzMLP(263 -> 256)`` (input role) and ``LipschitzMLP(256 -> 263)`` (output role),
for a fixed number of steps with ``loss = MSE + λ · lipschitz_loss``, for each ``w0`` and ``λ``.
Prints a Markdown table: reconstruction MSE (train, held-out val+test), the penalty
``Σ ∏ softplus(c)`` and the ∞-norm Lipschitz bounds of both MLPs. CPU, < 3 min on 2 cores.

    python scripts/choose_lipschitz_defaults.py [--steps 600] [--data DIR]
"""
from __future__ import annotations

import argparse
import os
import time
from typing import Dict, List, Tuple

import numpy as np
import torch
import torch.nn.functional as F

from smdm_plugin.core.lipschitz import LipschitzMLP, lipschitz_loss

DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                    "shared", "data", "cmu-humanml3d")


def load_frames(root: str) -> Tuple[torch.Tensor, torch.Tensor]:
    """Normalised frames ``[N, 263]`` of the train split and of val+test."""
    mean = np.load(os.path.join(root, "Mean.npy"))
    std = np.load(os.path.join(root, "Std.npy"))

    def split(names: List[str]) -> torch.Tensor:
        ids = [line.strip() for n in names
               for line in open(os.path.join(root, f"{n}.txt")) if line.strip()]
        x = np.concatenate([np.load(os.path.join(root, "new_joint_vecs", f"{i}.npy"))
                            for i in ids])
        return torch.from_numpy((x - mean) / (std + 1e-8)).float()

    return split(["train"]), split(["val", "test"])


def run(train: torch.Tensor, held: torch.Tensor, w0: float, lam: float, steps: int,
        batch: int, latent: int, layers: int, seed: int) -> Dict[str, float]:
    torch.manual_seed(seed)
    enc = LipschitzMLP(train.shape[1], latent, hidden=latent, layers=layers, w0=w0)
    dec = LipschitzMLP(latent, train.shape[1], hidden=latent, layers=layers, w0=w0)
    model = torch.nn.ModuleList([enc, dec])
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        x = train[torch.randint(len(train), (batch,), generator=g)]
        loss = F.mse_loss(dec(enc(x)), x) + lam * lipschitz_loss(model)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    with torch.no_grad():
        return {
            "train_mse": F.mse_loss(dec(enc(train)), train).item(),
            "val_mse": F.mse_loss(dec(enc(held)), held).item(),
            "penalty": lipschitz_loss(model).item(),
            "bound_in": enc.lipschitz_bound().item(),
            "bound_out": dec.lipschitz_bound().item(),
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=DATA)
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads (1 is fastest for these small matmuls on a busy box)")
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--latent", type=int, default=256)
    ap.add_argument("--layers", type=int, default=2)
    ap.add_argument("--w0", type=float, nargs="+", default=[1.0, 5.0, 30.0])
    ap.add_argument("--lam", type=float, nargs="+", default=[0.0, 1e-6, 1e-4, 1e-2])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.time()
    train, held = load_frames(args.data)
    print(f"frames: train {len(train)} (mean per-dim variance {train.var(0).mean():.2f}), "
          f"held-out val+test {len(held)} (variance {held.var(0).mean():.2f}); steps {args.steps}, "
          f"batch {args.batch}, Adam lr 1e-3, latent {args.latent}, layers {args.layers}\n")
    print("| w0 | λ | train MSE | held-out MSE | Σ∏softplus(c) | bound in (263→256) "
          "| bound out (256→263) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for w0 in args.w0:
        for lam in args.lam:
            r = run(train, held, w0, lam, args.steps, args.batch, args.latent, args.layers,
                    args.seed)
            print(f"| {w0:g} | {lam:g} | {r['train_mse']:.4f} | {r['val_mse']:.4f} | "
                  f"{r['penalty']:.3g} | {r['bound_in']:.3g} | {r['bound_out']:.3g} |",
                  flush=True)
    print(f"\n({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    main()
