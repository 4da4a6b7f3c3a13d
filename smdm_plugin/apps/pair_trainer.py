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
#: a crop and two numbers uniform in [0, 1) -> the augmented crop
Augment = Callable[[np.ndarray, float, float], np.ndarray]

#: HumanML3D's 22 joints: left and right counterparts (hips, knees, ankles, feet, collars, shoulders,
#: elbows, wrists), as HumanML3D's own mirroring swaps them
LEFT22 = (1, 4, 7, 10, 13, 16, 18, 20)
RIGHT22 = (2, 5, 8, 11, 14, 17, 19, 21)


def augment_joints22(crop: np.ndarray, u_angle: float, u_mirror: float) -> np.ndarray:
    """Joints ``[l, 22, 3]`` (y up) turned about the vertical axis through the first frame's root
    by ``2π u_angle`` and, when ``u_mirror < 0.5``, mirrored (x -> -x, left and right swapped)."""
    j = np.array(crop, dtype=np.float32)
    if u_mirror < 0.5:
        j[..., 0] *= -1
        j[:, LEFT22 + RIGHT22] = j[:, RIGHT22 + LEFT22]
    a = 2 * np.pi * u_angle
    c, s = np.cos(a), np.sin(a)
    o = j[0, 0, [0, 2]]
    x, z = j[..., 0] - o[0], j[..., 2] - o[1]
    j[..., 0], j[..., 2] = c * x + s * z + o[0], -s * x + c * z + o[1]
    return j


class CropSampler:
    """Batches ``(x [B, N, D] float32, lengths [B] long)`` of random crops.

    Args:
        motions: whole motions ``[L_i, ...]`` (any per-frame shape ``transform`` accepts).
        frames: ``N``, the padded length (and the longest crop).
        min_frames: the shortest crop; crops take a length uniform in ``[min_frames, min(L_i, N)]``
            (``min_frames == frames``: fixed-length crops).
        transform: a crop ``[l, ...]`` -> features ``[l, D]`` (e.g. canonicalise and encode joints).
        mean, std: ``[D]``, to normalise the features.
        augment: applied to each crop before ``transform`` (e.g. :func:`augment_joints22`).
    """

    def __init__(self, motions: Sequence[np.ndarray], frames: int, min_frames: int, transform: Transform,
                 mean: np.ndarray, std: np.ndarray, augment: Optional[Augment] = None) -> None:
        self.motions = [m for m in motions if len(m) >= min_frames]
        if not self.motions:
            raise ValueError(f"CropSampler: no motion has min_frames={min_frames} frames")
        if not 2 <= min_frames <= frames:
            raise ValueError(f"CropSampler: need 2 <= min_frames <= frames, got {min_frames}, {frames}")
        self.frames, self.min_frames, self.transform = int(frames), int(min_frames), transform
        self.mean, self.std = np.asarray(mean, np.float32), np.asarray(std, np.float32)
        self.augment = augment

    def __call__(self, batch: int, generator: torch.Generator) -> Tuple[torch.Tensor, torch.Tensor]:
        idx = torch.randint(0, len(self.motions), (batch,), generator=generator).tolist()
        u = torch.rand(batch, 4, generator=generator, dtype=torch.float64).numpy()
        x = np.zeros((batch, self.frames, self.mean.shape[0]), np.float32)
        lengths = []
        for b, i in enumerate(idx):
            m = self.motions[i]
            hi = min(len(m), self.frames)
            length = self.min_frames + int(u[b, 0] * (hi - self.min_frames + 1))
            start = int(u[b, 1] * (len(m) - length + 1))
            crop = m[start:start + length]
            if self.augment is not None:
                crop = self.augment(crop, float(u[b, 2]), float(u[b, 3]))
            x[b, :length] = (self.transform(crop) - self.mean) / self.std
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
                          mean=None, std=None, log_every: int = 0,
                          validate: Optional[Callable[[nn.Module, Any], float]] = None
                          ) -> Tuple[Dict[str, Any], Dict[str, Tuple[nn.Module, Any]]]:
    """Train the pair for ``seconds`` in total (time-sliced) or ``max_steps`` each, whichever
    comes first. Every ``log_every`` steps of a model (0: never) its mean recent loss is printed and
    ``validate(model, diffusion)`` (e.g. a held-out loss; run in ``eval`` mode, untimed) recorded.
    Returns ``(stats, pair)``: per model steps, seconds, steps/s, the loss curve, ``val``
    ``[(step, value)]``, and ``speed_ratio`` (sparse / dense steps per second); ``pair`` as
    :func:`build_pair`, trained (left in ``train`` mode)."""
    dev = torch.device(device)
    pair = build_pair(spec, dev, seed, mean, std)
    runs: Dict[str, Dict[str, Any]] = {}
    for name, (model, diffusion) in pair.items():
        runs[name] = {"model": model.train(), "diffusion": diffusion, "spent": 0.0, "steps": 0, "loss": [], "val": [],
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
        if log_every and r["steps"] % log_every == 0:
            line = f"{name} step {r['steps']}: loss {np.mean(r['loss'][-log_every:]):.4f}, {r['spent']:.0f} s"
            if validate is not None:
                r["model"].eval()
                with torch.no_grad():
                    r["val"].append((r["steps"], float(validate(r["model"], r["diffusion"]))))
                r["model"].train()
                line += f", validation {r['val'][-1][1]:.4f}"
            print(line, flush=True)
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
                       "loss": r["loss"], "time": r["time"], "val": r["val"]}
    stats["speed_ratio"] = stats["sparse"]["steps_per_s"] / max(stats["dense"]["steps_per_s"], 1e-9)
    return stats, pair


def feature_stats(features: List[np.ndarray], eps: float = 1e-4) -> Tuple[np.ndarray, np.ndarray]:
    """Mean and std ``[D]`` over every frame of ``features`` (``[L_i, D]`` each); std floored at ``eps``."""
    allf = np.concatenate(features, 0).astype(np.float64)
    return allf.mean(0).astype(np.float32), (allf.std(0) + eps).astype(np.float32)
