"""The in-package trainer: the reference :class:`~smdm_plugin.reference.backbone.TinyMDM` +
:class:`~smdm_plugin.reference.simple_diffusion.SimpleDiffusion`, dense or sparse, on HumanML3D-format
motion; one process, or many under ``torchrun`` (DistributedDataParallel)."""
from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
import torch.nn as nn

from ..adapters.state import sparse_config_of
from ..core.config import SparseConfig
from ..support.config_files import CONFIG_FILENAME
from ..runtime.compile import (CAPTURES_TRAIN, check_compile_mode, compile_function, compile_model,
                                    compile_setting, fused_optimizer_kwargs)
from ..runtime.distributed import DistContext, constant_buffers_kwargs, init_distributed
from ..io.checkpoint_files import BACKBONE_FILENAME, TRAIN_CONFIG_FILENAME
from ..io.files import atomic_open, atomic_write_json, atomic_write_text
from ..reference.text import TextConfig, save_text_config
from .data import MotionSet

#: TinyMDM size of ``smdm train`` / ``smdm ablate`` (MDM's HumanML3D size is 512-D, 8 layers, ff 1024)
DEFAULT_MODEL: Dict[str, Any] = {"latent_dim": 128, "num_layers": 4, "num_heads": 4, "ff_size": 256,
                                 "arch": "trans_enc", "dropout": 0.1}
#: optimiser, random streams and step of the last checkpoint (``smdm train --resume``)
TRAIN_STATE_FILENAME = "train_state.pt"
TRAIN_STATE_VERSION = 1
#: feature width -> the representation written to motion.json (HumanML3D 263-D and joints66, both 20 fps)
MOTION_REPRESENTATIONS: Dict[int, str] = {263: "humanml3d", 66: "joints66"}


# ----------------------------------------------------------------------------------------- randomness
_MASK64 = (1 << 64) - 1


def mix_seed(*values: int) -> int:
    """A 63-bit seed from integers (splitmix64 over them): nearby inputs give unrelated streams."""
    h = 0x9E3779B97F4A7C15
    for v in values:
        h = (h ^ (int(v) & _MASK64)) & _MASK64
        h = (h + 0x9E3779B97F4A7C15) & _MASK64
        z = h
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
        h = z ^ (z >> 31)
    return h & ((1 << 63) - 1)


def global_batch_indices(step: int, global_batch: int, n: int, seed: int) -> torch.Tensor:
    """The dataset indices ``[global_batch]`` of optimiser step ``step``: the next entries of an
    endless stream of epoch permutations (epoch ``e``: ``randperm(n)`` seeded by ``(seed, e)``).
    The same on every rank; rank ``r`` of ``W`` takes the slice ``[r*b, (r+1)*b)``."""
    start = step * global_batch
    pos = torch.arange(start, start + global_batch)
    epochs, where = pos // n, pos % n
    out = torch.empty(global_batch, dtype=torch.long)
    for e in torch.unique(epochs).tolist():
        perm = torch.randperm(n, generator=torch.Generator().manual_seed(mix_seed(seed, 1, e)))
        sel = epochs == e
        out[sel] = perm[where[sel]]
    return out


def diffusion_draws(seed: int, step: int, sample_ids: Sequence[int], num_timesteps: int,
                    shape: Tuple[int, ...], device: torch.device) -> Tuple[torch.Tensor, torch.Tensor]:
    """Each sample's diffusion step ``t [b]`` and noise ``[b, *shape]`` at ``step``, a function of
    ``(seed, step, global sample index)`` only (so the split of a batch over ranks does not matter)."""
    ts, noise = [], []
    for i in sample_ids:
        g = torch.Generator(device=device).manual_seed(mix_seed(seed, 2, step, int(i)))
        ts.append(torch.randint(0, num_timesteps, (1,), generator=g, device=device))
        noise.append(torch.randn(shape, generator=g, device=device))
    return torch.cat(ts), torch.stack(noise)


def caption_draws(seed: int, step: int, sample_ids: Sequence[int], counts: Sequence[int]) -> List[int]:
    """Which caption each sample uses at ``step``: ``[b]`` indices in ``[0, counts[k])``, a function of
    ``(seed, step, global sample index)`` only (as :func:`diffusion_draws`)."""
    return [int(torch.randint(0, int(c), (1,), generator=torch.Generator().manual_seed(mix_seed(seed, 5, step, int(i)))))
            for i, c in zip(sample_ids, counts)]


# ----------------------------------------------------------------------------------------- config
@dataclass
class TrainConfig:
    """What to train and how. ``batch`` is per process (global batch = ``batch * world_size``);
    ``model``: :class:`TinyMDM` keyword arguments (``njoints`` comes from the data); ``sparse``:
    None trains the dense model. ``grad_clip`` 0 = off. ``compile``: ``none`` | ``default`` |
    ``reduce-overhead`` (``True``/``False`` read as ``default``/``none``), with ``compile_backend``
    (docs/compile.md): one process captures the whole training step (the loss forward and backward,
    :func:`smdm_plugin.runtime.compile.compile_function`; AdamW fused on CUDA); under
    ``torchrun`` the model call is compiled in place, inside DDP
    (:func:`smdm_plugin.runtime.compile.compile_model`); either way the model's own call is
    compiled too (sampling with the trained model). ``text``: a
    :class:`~smdm_plugin.reference.text.TextConfig` trains text-conditioned (the data needs
    captions; one caption drawn per sample per step; condition dropout for classifier-free
    guidance); None (default) trains unconditionally."""

    steps: int = 1000
    batch: int = 16
    lr: float = 2e-4
    weight_decay: float = 0.0
    grad_clip: float = 0.0
    diffusion_steps: int = 100
    seed: int = 0
    model: Dict[str, Any] = field(default_factory=lambda: dict(DEFAULT_MODEL))
    sparse: Optional[SparseConfig] = None
    compile: str = "none"
    compile_backend: str = "inductor"
    text: Optional[TextConfig] = None

    def __post_init__(self) -> None:
        self.compile = check_compile_mode(self.compile, "TrainConfig.compile")
        checks = {"steps": self.steps >= 0, "batch": self.batch >= 1, "lr": self.lr > 0,
                  "weight_decay": self.weight_decay >= 0, "grad_clip": self.grad_clip >= 0,
                  "diffusion_steps": self.diffusion_steps >= 1}
        expected = {"steps": "an int >= 0", "batch": "an int >= 1", "lr": "a float > 0",
                    "weight_decay": "a float >= 0", "grad_clip": "a float >= 0 (0 = off)",
                    "diffusion_steps": "an int >= 1"}
        for name, ok in checks.items():
            if not ok or (isinstance(getattr(self, name), float) and not math.isfinite(getattr(self, name))):
                raise ValueError(f"TrainConfig.{name}={getattr(self, name)!r}: expected {expected[name]}")
        if self.sparse is not None and not isinstance(self.sparse, SparseConfig):
            raise TypeError(f"TrainConfig.sparse must be a SparseConfig or None, got {type(self.sparse).__name__}")
        if self.text is not None and not isinstance(self.text, TextConfig):
            raise TypeError(f"TrainConfig.text must be a TextConfig or None, got {type(self.text).__name__}")
        unknown = set(self.model) - set(_TINYMDM_ARGS)
        if unknown:
            raise ValueError(f"TrainConfig.model: unknown TinyMDM option(s) {sorted(unknown)}")

    def to_dict(self) -> Dict[str, Any]:
        d = dataclasses.asdict(self)
        d["sparse"] = None if self.sparse is None else self.sparse.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "TrainConfig":
        d = dict(d)
        if d.get("sparse") is not None and not isinstance(d["sparse"], SparseConfig):
            d["sparse"] = SparseConfig.from_dict(d["sparse"])
        if d.get("text") is not None and not isinstance(d["text"], TextConfig):
            d["text"] = TextConfig.from_dict(d["text"])
        return cls(**d)


_TINYMDM_ARGS = ("latent_dim", "ff_size", "num_layers", "num_heads", "dropout", "activation", "arch",
                 "emb_trans_dec", "mask_frames", "max_len")


@dataclass
class TrainResult:
    """What :meth:`Trainer.train` did: ``losses`` (per step, mean over every sample of the global
    batch), ``seconds`` (wall time spent in :meth:`Trainer.step`), ``world_size``,
    ``global_batch``, ``total_steps`` (the trainer's step count afterwards), ``max_divergence``
    (largest parameter or buffer difference between ranks after the last step; 0.0 = in sync)."""

    losses: List[float]
    seconds: float
    world_size: int
    global_batch: int
    total_steps: int
    max_divergence: float = 0.0

    @property
    def steps(self) -> int:
        return len(self.losses)

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else float("nan")

    @property
    def samples_per_s(self) -> float:
        return self.steps_per_s * self.global_batch

    @property
    def final_loss(self) -> float:
        """Mean loss of the last 10% of the steps (nan when none)."""
        if not self.losses:
            return float("nan")
        k = max(1, len(self.losses) // 10)
        return float(np.mean(self.losses[-k:]))

    @property
    def best_loss(self) -> float:
        """Lowest moving average (window: 10% of the steps)."""
        if not self.losses:
            return float("nan")
        k = max(1, len(self.losses) // 10)
        return float(np.convolve(self.losses, np.ones(k) / k, mode="valid").min())

    def to_dict(self) -> Dict[str, Any]:
        d = dataclasses.asdict(self)
        d.update(steps=self.steps, steps_per_s=self.steps_per_s, samples_per_s=self.samples_per_s,
                 final_loss=self.final_loss, best_loss=self.best_loss)
        return d


# ----------------------------------------------------------------------------------------- trainer
class Trainer:
    """TinyMDM + SimpleDiffusion training, dense or sparse, single process or DDP.

    Args:
        config: the :class:`TrainConfig`.
        data: the training :class:`MotionSet`.
        dist: where this process stands; None: :func:`init_distributed` (joins the ``torchrun``
            group when started by ``torchrun``, else a single process on ``device``).
        device: ``auto`` | ``cpu`` | ``cuda`` | ``cuda:N`` | ``mps`` (used when ``dist`` is None).

    Attributes: ``model`` (the plain module: save it, sample with it), ``diffusion``,
    ``optimizer``, ``dist``, ``step_count`` (optimiser steps so far), ``losses`` (all of them).
    """

    def __init__(self, config: TrainConfig, data: MotionSet, dist: Optional[DistContext] = None,
                 device: str = "auto", init_from: Optional[str] = None, init_amplitude: float = 0.05) -> None:
        from ..adapters.surgery import sparsify
        from ..reference.backbone import TinyMDM
        from ..reference.simple_diffusion import SimpleDiffusion

        if len(data) == 0:
            raise ValueError("Trainer: data holds no motion")
        self.config, self.data = config, data
        self.dist = dist if dist is not None else init_distributed(device)
        dev = self.dist.device
        torch.manual_seed(config.seed)  # initial weights: equal on every rank
        self.backbone_args: Dict[str, Any] = {"njoints": data.feature_dim, "nfeats": 1, "cond_mode": "no_cond",
                                              **config.model}
        self.text_embeddings: Optional[List[torch.Tensor]] = None
        if config.text is not None:
            if data.captions is None:
                raise ValueError("Trainer: config.text needs captions in the data (load_humanml3d(..., "
                                 "with_captions=True))")
            self.backbone_args.update(cond_mode="text", clip_dim=config.text.dim,
                                      cond_mask_prob=config.text.cond_mask_prob)
            enc = config.text.build()  # frozen: every caption embedded once, [n_captions_i, dim] per motion
            self.text_embeddings = [enc(caps) for caps in data.captions]
        self.model = TinyMDM(**self.backbone_args).to(dev)
        self.diffusion = SimpleDiffusion(config.diffusion_steps)
        #: where the initial weights came from (``init_from``: path, digest, fit errors), else None
        self.init_origin: Optional[Dict[str, Any]] = None
        if init_from is not None:   # dense weights in; sparse: new layers fitted to the dense ones
            self.init_origin = init_from_dense(self, init_from, amplitude=init_amplitude)
        elif config.sparse is not None:
            sparsify(self.model, config.sparse, diffusion=self.diffusion, mean=data.mean, std=data.std)
        self.model.train()
        self.forward_model: nn.Module = self.model
        #: how the training step runs (``none``: eager): the model compiled in place before DDP wraps
        #: it (its calls outside the step, and the step under torchrun), and one process's whole step
        self.compile_setting = compile_model(self.model, config.compile, backend=config.compile_backend,
                                             device=dev, name="TrainConfig.compile")
        self._loss: Callable[..., torch.Tensor] = self.training_loss
        if self.dist.distributed:
            from torch.nn.parallel import DistributedDataParallel

            self.forward_model = DistributedDataParallel(
                self.model, device_ids=[dev.index] if dev.type == "cuda" else None, **constant_buffers_kwargs())
            if config.compile != "none":
                self.compile_setting.captures += " (inside DDP)"
        elif config.compile != "none":
            self._loss = compile_function(self.training_loss, config.compile, model=self.model,
                                          backend=config.compile_backend, device=dev, name="TrainConfig.compile",
                                          captures=CAPTURES_TRAIN)
            self.compile_setting = compile_setting(self._loss)
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=config.lr, weight_decay=config.weight_decay,
                                           **fused_optimizer_kwargs(dev, config.compile))
        # dropout: a stream of its own on each rank (mask noise: the model's table, core/noise.py)
        torch.manual_seed(mix_seed(config.seed, 3, self.dist.rank))
        self.step_count = 0
        self.losses: List[float] = []

    @property
    def global_batch(self) -> int:
        return self.config.batch * self.dist.world_size

    def batch_indices(self, step: int) -> torch.Tensor:
        """This rank's dataset indices ``[batch]`` at ``step``."""
        ids = global_batch_indices(step, self.global_batch, len(self.data), self.config.seed)
        b = self.config.batch
        return ids[self.dist.rank * b:(self.dist.rank + 1) * b]

    def step(self) -> float:
        """One optimiser step on this rank's shard of the next global batch; returns the loss
        averaged over the whole global batch (every rank gets the same value)."""
        dev, b, N = self.dist.device, self.config.batch, self.data.max_frames
        ids = self.batch_indices(self.step_count)
        x, lengths = self.data.padded(ids)
        x = x.permute(0, 2, 1).unsqueeze(2).to(dev)  # [b, D, 1, N]
        lengths = lengths.to(dev)
        sample_ids = range(self.step_count * self.global_batch + self.dist.rank * b,
                           self.step_count * self.global_batch + (self.dist.rank + 1) * b)
        t, noise = diffusion_draws(self.config.seed, self.step_count, sample_ids, self.diffusion.num_timesteps,
                                   tuple(x.shape[1:]), dev)
        y = {"mask": (torch.arange(N, device=dev) < lengths[:, None]).view(b, 1, 1, N), "lengths": lengths}
        if self.text_embeddings is not None:
            embs = [self.text_embeddings[i] for i in ids.tolist()]
            pick = caption_draws(self.config.seed, self.step_count, sample_ids, [len(e) for e in embs])
            y["text_embed"] = torch.stack([e[k] for e, k in zip(embs, pick)]).unsqueeze(0).to(dev)  # [1, b, dim]
        loss = self._loss(x, t, {"y": y}, noise)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.config.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.config.grad_clip)
        self.optimizer.step()
        value = float(self.dist.mean(loss.detach()))
        if not math.isfinite(value):
            raise FloatingPointError(f"Trainer: the loss became {value} at step {self.step_count}")
        self.step_count += 1
        self.losses.append(value)
        return value

    def training_loss(self, x: torch.Tensor, t: torch.Tensor, model_kwargs: Dict[str, Any],
                      noise: torch.Tensor) -> torch.Tensor:
        """The mean loss of this rank's batch: ``x [b, D, 1, N]``, steps ``t [b]``, ``noise`` like
        ``x`` (the sparse diffusion wrapper's keyframe selection included); what a compiled run
        captures whole."""
        return self.diffusion.training_losses(self.forward_model, x, t, model_kwargs, noise=noise)["loss"].mean()

    def train(self, steps: Optional[int] = None, progress: bool = False,
              callback: Optional[Callable[["Trainer", float], None]] = None) -> TrainResult:
        """Run ``steps`` more optimiser steps (default: up to ``config.steps`` in total);
        ``callback(trainer, loss)`` after each; a tqdm bar (with ETA) on rank 0 when ``progress``."""
        n = max(0, self.config.steps - self.step_count) if steps is None else int(steps)
        if n < 0:
            raise ValueError(f"Trainer.train: steps must be >= 0, got {steps}")
        bar = None
        from ..support.progress import bars_on  # stderr a terminal (or --progress)

        if self.dist.is_main and bars_on(progress):
            from tqdm.auto import tqdm

            bar = tqdm(total=n, desc="sparse" if self.config.sparse is not None else "dense",
                       unit="step", mininterval=0.5)
        losses: List[float] = []
        seconds = 0.0  # in step() only: not the progress bar, not the callback (checkpoints)
        for _ in range(n):
            t0 = time.perf_counter()
            losses.append(self.step())
            seconds += time.perf_counter() - t0
            if bar is not None:
                bar.set_postfix_str(f"loss {np.mean(losses[-20:]):.4f}", refresh=False)
                bar.update(1)
            if callback is not None:
                callback(self, losses[-1])
        if bar is not None:
            bar.close()
        return TrainResult(losses=losses, seconds=seconds, world_size=self.dist.world_size,
                           global_batch=self.global_batch, total_steps=self.step_count,
                           max_divergence=self.dist.max_divergence(self.model))

    # ------------------------------------------------------------------------------ checkpoints
    def checkpoint_name(self) -> str:
        return f"model{self.step_count:09d}.pt"

    def state(self) -> Dict[str, Any]:
        """What :meth:`load_state` needs to continue exactly where this trainer stands: step count,
        losses, optimiser state, and every random stream (torch CPU / CUDA, numpy, Python's
        ``random``); plain tensors and containers (loads with ``weights_only=True``). The data
        order, diffusion steps and noise are functions of (seed, step) and need no state. Under
        torchrun every rank must call it (the random streams of all ranks are gathered: ``rng``
        holds one entry per rank)."""
        rngs = [self._rng_state()]
        if self.dist.distributed:
            rngs = [None] * self.dist.world_size
            torch.distributed.all_gather_object(rngs, self._rng_state())
        return {"format": TRAIN_STATE_VERSION, "step": self.step_count, "world_size": self.dist.world_size,
                "config": json.dumps(self.config.to_dict(), sort_keys=True),
                "losses": torch.tensor(self.losses, dtype=torch.float64),
                "optimizer": self.optimizer.state_dict(), "rng": rngs}

    def _rng_state(self) -> Dict[str, Any]:
        """This process's random streams as tensors and plain values."""
        import random

        np_state = np.random.get_state()
        py_state = random.getstate()
        return {"torch": torch.get_rng_state(),
                "cuda": torch.cuda.get_rng_state(self.dist.device) if self.dist.device.type == "cuda" else None,
                "numpy": [np_state[0], torch.from_numpy(np_state[1].astype(np.int64)), int(np_state[2]),
                          int(np_state[3]), float(np_state[4])],
                "python": [py_state[0], torch.tensor(py_state[1], dtype=torch.int64), py_state[2]]}

    def load_state(self, state: Dict[str, Any], weights: Dict[str, torch.Tensor], where: str = "state") -> None:
        """Continue from :meth:`state` (and the model ``weights`` of the same step). Raises
        ``ValueError`` naming ``where`` when it does not belong to this run (another config, other
        world size, a newer format)."""
        import random

        if not isinstance(state, dict) or state.get("format") != TRAIN_STATE_VERSION:
            raise ValueError(f"{where}: not a training state of format {TRAIN_STATE_VERSION}")
        missing = [k for k in ("step", "world_size", "config", "losses", "optimizer", "rng") if k not in state]
        if missing:
            raise ValueError(f"{where}: missing field(s) {', '.join(missing)}")
        saved = json.loads(state["config"])
        now = self.config.to_dict()
        same = ("steps", "compile", "compile_backend")  # how it runs, not what it trains: may change on resume
        differ = sorted(k for k in set(saved) | set(now) if k not in same and saved.get(k) != now.get(k))
        if differ:
            raise ValueError(f"{where}: saved by a run with other settings ({'; '.join(f'{k}: saved {saved.get(k)!r}, now {now.get(k)!r}' for k in differ)})")
        if int(state["world_size"]) != self.dist.world_size or len(state["rng"]) != self.dist.world_size:
            raise ValueError(f"{where}: saved by {state['world_size']} process(es), resumed with {self.dist.world_size}")
        step = int(state["step"])
        losses = state["losses"]
        if step < 0 or not isinstance(losses, torch.Tensor) or losses.shape != (step,):
            raise ValueError(f"{where}: step {step} and {tuple(getattr(losses, 'shape', ()))} losses disagree")
        self.model.load_state_dict(weights)
        self.optimizer.load_state_dict(state["optimizer"])
        rng = state["rng"][self.dist.rank]  # this rank's streams
        torch.set_rng_state(rng["torch"])
        if rng.get("cuda") is not None and self.dist.device.type == "cuda":
            torch.cuda.set_rng_state(rng["cuda"], self.dist.device)
        n = rng["numpy"]
        np.random.set_state((n[0], n[1].numpy().astype(np.uint32), int(n[2]), int(n[3]), float(n[4])))
        p = rng["python"]
        random.setstate((p[0], tuple(int(v) for v in p[1].tolist()), p[2]))
        self.step_count = step
        self.losses = [float(v) for v in losses.tolist()]

    def save(self, folder: str, extra: Optional[Dict[str, Any]] = None) -> Optional[str]:
        """Write the checkpoint folder (rank 0 only; other ranks return None): ``model<step>.pt``
        (the plain model's state dict), ``backbone.json`` (TinyMDM arguments), ``sparse_config.json``
        (sparse models), ``Mean.npy``/``Std.npy``, ``train_config.json`` (+ ``extra``) and, for 263-D
        or 66-D features, ``motion.json`` (so ``smdm inbetween --model`` reads the folder); each file
        written atomically. :func:`smdm_plugin.load_checkpoint` reloads it. The caller checks
        that ``folder`` may be written (``io.files.check_new_dir``). Under torchrun every rank
        calls it (the training state gathers every rank's random streams)."""
        state = self.state()
        if not self.dist.is_main:
            return None
        os.makedirs(folder, exist_ok=True)
        path = os.path.join(folder, self.checkpoint_name())
        with atomic_open(path, "wb") as f:
            torch.save({k: v.detach().cpu() for k, v in self.model.state_dict().items()}, f)
        atomic_write_json(os.path.join(folder, BACKBONE_FILENAME), self.backbone_args)
        config = sparse_config_of(self.model)
        if config is not None:
            atomic_write_text(os.path.join(folder, CONFIG_FILENAME), config.to_json() + "\n")
        if self.config.text is not None:
            save_text_config(folder, self.config.text)
        for name, value in (("Mean.npy", self.data.mean), ("Std.npy", self.data.std)):
            with atomic_open(os.path.join(folder, name), "wb") as f:
                np.save(f, np.asarray(value, np.float32))
        atomic_write_json(os.path.join(folder, TRAIN_CONFIG_FILENAME),
                          {**self.config.to_dict(), "world_size": self.dist.world_size,
                           "global_batch": self.global_batch, "step": self.step_count,
                           **({"init_from": self.init_origin} if self.init_origin else {}), **(extra or {})})
        rep = MOTION_REPRESENTATIONS.get(self.data.feature_dim)
        if rep is not None:  # motion.json: the folder is also a model smdm inbetween reads (training.bundle)
            from .bundle import write_motion_meta
            from ..io.representation import Representation

            write_motion_meta(folder, Representation(rep), self.data.mean, self.data.std, 20.0,
                              self.data.max_frames, self.diffusion.num_timesteps,
                              {"trained_by": "smdm train", "steps": self.step_count})
        # last: its presence means the checkpoint of its step is complete
        with atomic_open(os.path.join(folder, TRAIN_STATE_FILENAME), "wb") as f:
            torch.save(state, f)
        return path


def race_fair(trainers: Dict[str, "Trainer"], seconds: float = float("inf"), max_steps: Optional[int] = None,
              progress: bool = False, desc: str = "training") -> Dict[str, Any]:
    """Train several :class:`Trainer` s to **equal steps and equal time** (e.g. dense vs sparse).

    Phase 1, equal steps: every trainer makes one step in turn (so machine load hits all alike)
    until the slowest has spent ``seconds / len(trainers)`` in :meth:`Trainer.step` (or made
    ``max_steps``); all now have ``S`` steps. The state of every other trainer at ``S`` steps is kept
    (``out['equal_steps']['states'][name]``, a CPU copy of ``model.state_dict()``). Phase 2, equal
    time: each faster trainer trains on until it has spent as long as the slowest (or made
    ``max_steps``). Under torchrun the times are averaged over the ranks, so every rank steps the
    same trainers (DDP needs that). Every trainer spends about ``seconds / len(trainers)``, so the
    whole run takes about ``seconds``. Phase 2 runs the faster trainers alone, so the load of the
    machine may differ from phase 1.

    Returns per trainer the equal-time run: ``steps``, ``seconds``, ``steps_per_s``,
    ``final_loss`` (mean of the last 10% of the losses), ``loss [steps]``, ``time [steps]`` (cumulative s) plus ``equal_steps``: ``{'steps': S,
    'seconds': {name: time at S}, 'final_loss': {name: loss over the last 10% of the S steps},
    'states': {name: state dict at S for the trainers that went on}}``, and ``speed_ratio``
    (second / first trainer's steps per second, phase 1)."""
    if not trainers:
        raise ValueError("race_fair: no trainers given")
    if not (seconds > 0) or (max_steps is not None and max_steps < 0) or (math.isinf(seconds) and max_steps is None):
        raise ValueError(f"race_fair: need seconds > 0 and max_steps >= 0 (one of them finite), got {seconds}, "
                         f"{max_steps}")
    names = list(trainers)
    dist = trainers[names[0]].dist
    share = seconds / len(names)
    spent = torch.zeros(len(names), dtype=torch.float64)
    runs: Dict[str, Dict[str, Any]] = {n: {"steps": 0, "seconds": 0.0, "loss": [], "time": []} for n in names}
    bar = None
    from ..support.progress import bars_on  # stderr a terminal (or --progress)

    if dist.is_main and bars_on(progress):
        from tqdm.auto import tqdm

        bar = tqdm(total=round(seconds) if math.isfinite(seconds) else len(names) * max_steps,
                   desc=desc + (" (s)" if math.isfinite(seconds) else ""), mininterval=0.5,
                   bar_format="{l_bar}{bar}| {n:.0f}/{total_fmt} [{elapsed}<{remaining}]{postfix}")

    def agreed() -> torch.Tensor:
        return dist.mean(spent.to(dist.device)).cpu() if dist.distributed else spent

    def step(i: int) -> None:
        r = runs[names[i]]
        t0 = time.perf_counter()
        r["loss"].append(trainers[names[i]].step())
        dt = time.perf_counter() - t0
        spent[i] += dt
        r["steps"] += 1
        r["seconds"] += dt
        r["time"].append(r["seconds"])
        if bar is not None:
            bar.set_postfix_str(", ".join(f"{n} {v['steps']} steps loss {np.mean(v['loss'][-10:]):.3f}"
                                          for n, v in runs.items() if v["loss"]), refresh=False)
            done = min(seconds, float(spent.sum())) if math.isfinite(seconds) else sum(
                v["steps"] for v in runs.values())
            bar.update(done - bar.n)

    # phase 1: equal steps (lockstep, alternating who goes first)
    S = 0
    while float(agreed().max()) < share and not (max_steps is not None and S >= max_steps):
        for i in (range(len(names)) if S % 2 == 0 else reversed(range(len(names)))):
            step(i)
        S += 1
    at_s = {n: {"seconds": runs[n]["seconds"], "final_loss": _tail_mean(runs[n]["loss"])} for n in names}
    limit = float(agreed().max())
    slowest = int(agreed().argmax())
    states = {}
    for i, n in enumerate(names):
        if i != slowest and float(agreed()[i]) < limit and not (max_steps is not None and S >= max_steps):
            states[n] = {k: v.detach().cpu().clone() for k, v in trainers[n].model.state_dict().items()}
    # phase 2: equal time
    for i, n in enumerate(names):
        if n not in states:
            continue
        while float(agreed()[i]) < limit and not (max_steps is not None and runs[n]["steps"] >= max_steps):
            step(i)
    if bar is not None:
        bar.close()
    out: Dict[str, Any] = {}
    for n, r in runs.items():
        out[n] = {**r, "steps_per_s": r["steps"] / max(r["seconds"], 1e-9),
                  "final_loss": _tail_mean(r["loss"]) if r["loss"] else None}
    out["equal_steps"] = {"steps": S, "seconds": {n: v["seconds"] for n, v in at_s.items()},
                          "final_loss": {n: v["final_loss"] for n, v in at_s.items()}, "states": states}
    if len(names) >= 2:
        rate = [S / max(at_s[n]["seconds"], 1e-9) for n in names[:2]]
        out["speed_ratio"] = rate[1] / max(rate[0], 1e-9)
    return out


def _tail_mean(losses: Sequence[float]) -> Optional[float]:
    """Mean of the last 10% of ``losses`` (None when empty)."""
    if not losses:
        return None
    k = max(1, len(losses) // 10)
    return float(np.mean(losses[-k:]))


def load_trained(folder: str, step: Optional[int] = None, map_location: Any = "cpu"
                 ) -> Tuple[nn.Module, Optional[SparseConfig]]:
    """Reload a folder written by :meth:`Trainer.save` (the last ``model*.pt``, or ``step``'s),
    sparse mode re-created with the saved Mean/Std: ``(model, sparse config or None)``."""
    import re
    from ..adapters.checkpoint import load_checkpoint

    from ..io.validate import check_stats, int_field, load_npy, read_json_object, require_fields

    if not os.path.isdir(folder):
        raise FileNotFoundError(f"load_trained: no such model folder: {folder!r}")
    names = sorted(n for n in os.listdir(folder) if re.fullmatch(r"model\d{9}\.pt", n))
    if step is not None:
        names = [n for n in names if n == f"model{step:09d}.pt"]
    if not names:
        raise FileNotFoundError(f"load_trained: no model{'*' if step is None else f'{step:09d}'}.pt in {folder}")
    # every saved setting checked before it is used: a wrong one is an error naming file and field
    bpath = os.path.join(folder, BACKBONE_FILENAME)
    backbone = read_json_object(bpath)
    D = int_field(backbone, "njoints", bpath) * int_field(backbone, "nfeats", bpath)
    cpath = os.path.join(folder, TRAIN_CONFIG_FILENAME)
    if os.path.exists(cpath):
        saved = read_json_object(cpath)
        require_fields(saved, ("steps", "diffusion_steps", "seed", "model", "sparse"), cpath)
        int_field(saved, "steps", cpath, lo=0)
        int_field(saved, "diffusion_steps", cpath, lo=1)
    mean = load_npy(os.path.join(folder, "Mean.npy"), "feature mean")
    std = load_npy(os.path.join(folder, "Std.npy"), "feature std")
    mean, _ = check_stats(mean, np.ones(D), D, os.path.join(folder, "Mean.npy"))
    _, std = check_stats(mean, std, D, os.path.join(folder, "Std.npy"))
    # the files of the run agreeing with each other: io.checkpoint.check_run_files, as every load does
    return load_checkpoint(os.path.join(folder, names[-1]), map_location=map_location, mean=mean, std=std)


def resume(trainer: "Trainer", folder: str) -> str:
    """Load ``folder``'s ``train_state.pt`` and the model of its step into ``trainer``; returns a
    line saying what was resumed (nothing when the interrupted run saved no checkpoint yet)."""
    import re

    path = os.path.join(folder, TRAIN_STATE_FILENAME)
    if not os.path.exists(path):
        names = os.listdir(folder) if os.path.isdir(folder) else []
        saved = sorted(n for n in names if re.fullmatch(r"model\d{9}\.pt", n))
        if saved:  # checkpoints without the state that continues them: never a silent restart over them
            raise ValueError(f"--resume: {folder} holds checkpoints ({', '.join(saved[-2:])}) but no "
                             f"{TRAIN_STATE_FILENAME} (the optimizer state and step to continue from); restore it, "
                             "or pass --overwrite to start over")
        return "no checkpoint saved yet; starting at step 0"
    from ..io.checkpoint_files import read_state_dict

    state = read_state_dict(path, what="training state")
    step = int(state.get("step", -1)) if isinstance(state, dict) else -1
    weights = read_state_dict(os.path.join(folder, f"model{step:09d}.pt"))
    trainer.load_state(state, weights, where=path)
    try:  # a warm-started run keeps its record of the dense origin
        with open(os.path.join(folder, TRAIN_CONFIG_FILENAME), encoding="utf-8") as f:
            origin = json.load(f).get("init_from")
        trainer.init_origin = origin if isinstance(origin, dict) else trainer.init_origin
    except (OSError, ValueError, AttributeError):
        pass
    if trainer.step_count > trainer.config.steps:
        raise ValueError(f"--resume: {path} is at step {trainer.step_count}, past --steps {trainer.config.steps}")
    return f"resumed at step {trainer.step_count}"


def dense_checkpoint_path(path: str) -> str:
    """The weights file of ``path``: a ``model*.pt`` file, or a folder's last one (``FileNotFoundError``
    naming ``path`` when there is none)."""
    import re

    if os.path.isdir(path):
        names = sorted(n for n in os.listdir(path) if re.fullmatch(r"model\d{9}\.pt", n))
        if not names:
            raise FileNotFoundError(f"--init-from: no model*.pt in {path!r}")
        return os.path.join(path, names[-1])
    if not os.path.isfile(path):
        raise FileNotFoundError(f"--init-from: no such checkpoint: {path!r}")
    return path


def init_from_dense(trainer: "Trainer", path: str, probe_motions: int = 16, amplitude: float = 0.05) -> Dict[str, Any]:
    """Load a dense checkpoint (``smdm train --out`` folder or its ``model*.pt``) into ``trainer``'s
    freshly built dense model; when the run is sparse, sparsify it with the new layers fitted to the
    dense ones on noised training motions (:func:`smdm_plugin.adapters.warm.warm_start`). The
    optimiser is built afterwards (fresh). Returns the origin record (path, content digest, fit
    errors). ``ValueError`` naming the file when it is sparse or of another TinyMDM size."""
    from ..adapters.warm import diffusion_probe, file_digest, warm_start
    from ..io.checkpoint_files import read_state_dict, state_dict_is_sparse

    weights = dense_checkpoint_path(path)
    sd = read_state_dict(weights)
    if state_dict_is_sparse(sd):
        raise ValueError(f"--init-from: {weights} holds a sparse model; continue it with --resume, or start from a "
                         "dense checkpoint")
    bpath = os.path.join(os.path.dirname(os.path.abspath(weights)), BACKBONE_FILENAME)
    if os.path.isfile(bpath):
        with open(bpath, encoding="utf-8") as f:
            saved = json.load(f)
        differ = {k: (saved.get(k), v) for k, v in trainer.backbone_args.items() if saved.get(k, v) != v}
        if differ:
            raise ValueError(f"--init-from: {bpath} describes another model ("
                             + "; ".join(f"{k}: saved {a!r}, now {b!r}" for k, (a, b) in differ.items())
                             + "); pass the same model options")
    try:
        trainer.model.load_state_dict(sd)
    except RuntimeError as e:
        raise ValueError(f"--init-from: {weights} does not fit the model: {str(e).splitlines()[0]}") from None
    origin: Dict[str, Any] = {"path": os.path.abspath(weights), "digest": file_digest(weights)}
    config = trainer.config.sparse
    if config is None:
        return origin
    data, dev = trainer.data, trainer.dist.device
    ids = torch.arange(min(probe_motions, len(data)))
    x, lengths = data.padded(ids)
    x = x.permute(0, 2, 1).unsqueeze(2).to(dev)                     # [b, D, 1, N]
    N = data.max_frames
    y: Dict[str, Any] = {"mask": (torch.arange(N, device=dev) < lengths.to(dev)[:, None]).view(len(ids), 1, 1, N),
                         "lengths": lengths.to(dev)}
    if trainer.text_embeddings is not None:
        y["text_embed"] = torch.stack([trainer.text_embeddings[int(i)][0] for i in ids]).unsqueeze(0).to(dev)
    probe = diffusion_probe(x, {"y": y}, trainer.diffusion.q_sample, trainer.diffusion.num_timesteps,
                            seed=trainer.config.seed)
    report = warm_start(trainer.model, config, probe, diffusion=trainer.diffusion, mean=data.mean, std=data.std,
                        amplitude=amplitude)
    origin["amplitude"] = amplitude
    origin["fit"] = report.to_dict()
    origin["fit_summary"] = report.summary()
    return origin
