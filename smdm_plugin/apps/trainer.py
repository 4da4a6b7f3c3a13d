"""Train the in-package backbone dense and sparse side by side on the same batches (``smdm demo``,
``scripts/eval_inbetween.py``).

Both copies start from the same weights and see the same batches and diffusion steps; each training
step goes to the copy that has used less time so far (time-slicing), so machine load hits both
alike and the measured steps/s ratio is fair. Batches come from :class:`CropSampler`: random crops
of variable length from whole motions, padded to ``N`` frames with MDM's valid-frame mask.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
import torch.nn as nn

Transform = Callable[[np.ndarray], np.ndarray]


class CropSampler:
    """Batches ``(x [B, N, D] float32, lengths [B] long)`` of random crops.

    Args:
        motions: whole motions ``[L_i, ...]`` (any per-frame shape ``transform`` accepts).
        frames: ``N``, the padded length (and the longest crop).
        min_frames: the shortest crop; crops take a length uniform in ``[min_frames, min(L_i, N)]``
            (``min_frames == frames``: fixed-length crops).
        transform: a crop ``[l, ...]`` -> features ``[l, D]`` (e.g. canonicalise and encode joints).
        mean, std: ``[D]``, to normalise the features.
    """

    def __init__(self, motions: Sequence[np.ndarray], frames: int, min_frames: int, transform: Transform,
                 mean: np.ndarray, std: np.ndarray) -> None:
        self.motions = [m for m in motions if len(m) >= min_frames]
        if not self.motions:
            raise ValueError(f"CropSampler: no motion has min_frames={min_frames} frames")
        if not 2 <= min_frames <= frames:
            raise ValueError(f"CropSampler: need 2 <= min_frames <= frames, got {min_frames}, {frames}")
        self.frames, self.min_frames, self.transform = int(frames), int(min_frames), transform
        self.mean, self.std = np.asarray(mean, np.float32), np.asarray(std, np.float32)

    def __call__(self, batch: int, generator: torch.Generator) -> Tuple[torch.Tensor, torch.Tensor]:
        idx = torch.randint(0, len(self.motions), (batch,), generator=generator).tolist()
        u = torch.rand(batch, 2, generator=generator, dtype=torch.float64).numpy()
        x = np.zeros((batch, self.frames, self.mean.shape[0]), np.float32)
        lengths = []
        for b, i in enumerate(idx):
            m = self.motions[i]
            hi = min(len(m), self.frames)
            length = self.min_frames + int(u[b, 0] * (hi - self.min_frames + 1))
            start = int(u[b, 1] * (len(m) - length + 1))
            x[b, :length] = (self.transform(m[start:start + length]) - self.mean) / self.std
            lengths.append(length)
        return torch.from_numpy(x), torch.tensor(lengths)


@dataclass
class BackboneSpec:
    """``TinyMDM`` size and the diffusion / sparse settings of a dense-vs-sparse pair."""

    features: int
    latent: int = 256
    layers: int = 4
    heads: int = 4
    dropout: float = 0.1
    diffusion_steps: int = 100
    reduction: float = 0.8
    selection_feature: str = "raw"   # SparseConfig.feature
    lr: float = 2e-4

    def backbone_kwargs(self) -> Dict[str, Any]:
        return dict(njoints=self.features, nfeats=1, latent_dim=self.latent, ff_size=2 * self.latent,
                    num_layers=self.layers, num_heads=self.heads, cond_mode="no_cond", dropout=self.dropout)


def build_pair(spec: BackboneSpec, device: torch.device, seed: int, mean=None, std=None
               ) -> Dict[str, Tuple[nn.Module, Any]]:
    """``{'dense': (model, diffusion), 'sparse': (model, diffusion)}`` from the same initial weights."""
    from ..adapters.mdm import sparsify
    from ..core.config import SparseConfig
    from ..reference.backbone import TinyMDM
    from ..reference.diffusion import SimpleDiffusion

    pair = {}
    for name in ("dense", "sparse"):
        torch.manual_seed(seed)
        model = TinyMDM(**spec.backbone_kwargs()).to(device)
        diffusion = SimpleDiffusion(spec.diffusion_steps)
        if name == "sparse":
            sparsify(model, SparseConfig(reduction=spec.reduction, feature=spec.selection_feature),
                     diffusion=diffusion, mean=mean, std=std)
        pair[name] = (model, diffusion)
    return pair


def _y(lengths: torch.Tensor, N: int, device: torch.device) -> Dict[str, Any]:
    lengths = lengths.to(device)
    return {"mask": (torch.arange(N, device=device)[None] < lengths[:, None]).view(-1, 1, 1, N),
            "lengths": lengths}


def train_dense_vs_sparse(sample_batch: Callable[[int, torch.Generator], Tuple[torch.Tensor, torch.Tensor]],
                          spec: BackboneSpec, seconds: float, batch: int = 32, device: Any = "cpu",
                          seed: int = 0, max_steps: Optional[int] = None, progress: bool = True,
                          mean=None, std=None) -> Tuple[Dict[str, Any], Dict[str, Tuple[nn.Module, Any]]]:
    """Train the pair for ``seconds`` in total (time-sliced) or ``max_steps`` each, whichever
    comes first. Returns ``(stats, pair)``: per model steps, seconds, steps/s, the loss curve, and
    ``speed_ratio`` (sparse / dense steps per second); ``pair`` as :func:`build_pair`, trained
    (left in ``train`` mode)."""
    dev = torch.device(device)
    pair = build_pair(spec, dev, seed, mean, std)
    runs: Dict[str, Dict[str, Any]] = {}
    for name, (model, diffusion) in pair.items():
        runs[name] = {"model": model.train(), "diffusion": diffusion, "spent": 0.0, "steps": 0, "loss": [],
                      "time": [], "opt": torch.optim.AdamW(model.parameters(), lr=spec.lr),
                      "gen": torch.Generator().manual_seed(seed)}
    warm = torch.Generator().manual_seed(seed + 1)
    x, lengths = sample_batch(batch, warm)
    for r in runs.values():  # one untimed warm-up step each (allocations, lazy optimiser state)
        xx = x.permute(0, 2, 1).unsqueeze(2).to(dev)
        t = torch.zeros(x.shape[0], dtype=torch.long, device=dev)
        r["diffusion"].training_losses(r["model"], xx, t, {"y": _y(lengths, x.shape[1], dev)})["loss"].mean().backward()
        r["model"].zero_grad(set_to_none=True)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        if max_steps and not np.isfinite(seconds):
            bar = tqdm(total=2 * max_steps, desc="training dense + sparse", unit="step", mininterval=0.5)
        else:
            bar = tqdm(total=round(seconds), desc="training dense + sparse (s)", mininterval=0.5,
                       bar_format="{l_bar}{bar}| {n:.0f}/{total_fmt} s [{elapsed}<{remaining}]{postfix}")
    while True:
        live = [k for k, v in runs.items() if v["spent"] < seconds / 2 and not (max_steps and v["steps"] >= max_steps)]
        if not live:
            break
        name = min(live, key=lambda k: runs[k]["spent"])
        r = runs[name]
        x, lengths = sample_batch(batch, r["gen"])  # same batches for both copies
        t = torch.randint(0, r["diffusion"].num_timesteps, (batch,), generator=r["gen"]).to(dev)
        xx = x.permute(0, 2, 1).unsqueeze(2).to(dev)
        t0 = time.perf_counter()
        loss = r["diffusion"].training_losses(r["model"], xx, t, {"y": _y(lengths, x.shape[1], dev)})["loss"].mean()
        r["opt"].zero_grad(set_to_none=True)
        loss.backward()
        r["opt"].step()
        r["spent"] += time.perf_counter() - t0
        r["steps"] += 1
        r["loss"].append(loss.item())
        r["time"].append(r["spent"])
        if bar is not None:
            bar.set_postfix_str(", ".join(f"{k} {v['steps']} steps loss {np.mean(v['loss'][-10:]):.3f}"
                                          for k, v in runs.items() if v["loss"]), refresh=False)
            done = (runs["dense"]["steps"] + runs["sparse"]["steps"] if bar.unit == "step"
                    else min(seconds, runs["dense"]["spent"] + runs["sparse"]["spent"]))
            bar.update(done - bar.n)  # refreshes at most every mininterval
    if bar is not None:
        bar.close()
    stats: Dict[str, Any] = {"spec": asdict(spec), "batch": batch, "seed": seed}
    for name, r in runs.items():
        k = max(1, len(r["loss"]) // 10)
        stats[name] = {"steps": r["steps"], "seconds": r["spent"],
                       "steps_per_s": r["steps"] / max(r["spent"], 1e-9),
                       "final_loss": float(np.mean(r["loss"][-k:])) if r["loss"] else None,
                       "loss": r["loss"], "time": r["time"]}
    stats["speed_ratio"] = stats["sparse"]["steps_per_s"] / max(stats["dense"]["steps_per_s"], 1e-9)
    return stats, pair


def feature_stats(features: List[np.ndarray], eps: float = 1e-4) -> Tuple[np.ndarray, np.ndarray]:
    """Mean and std ``[D]`` over every frame of ``features`` (``[L_i, D]`` each); std floored at ``eps``."""
    allf = np.concatenate(features, 0).astype(np.float64)
    return allf.mean(0).astype(np.float32), (allf.std(0) + eps).astype(np.float32)
