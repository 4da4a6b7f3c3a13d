"""``smdm bench``: what sparse keyframe mode saves, dense and sparse side by side in one run.

For one registered model family (``--family``; each has a :class:`Workload`): ``mdm``, the
MDM-size in-package backbone (:class:`~smdm_plugin.reference.backbone.TinyMDM`, latent 512, 8
layers, 4 heads, ff 1024; ``trans_enc`` and ``trans_dec``), or ``motiondiffuse``, MotionDiffuse's
denoiser layout (:class:`~smdm_plugin.reference.motiondiffuse_denoiser.MotionDiffuseDenoiser`, latent 512,
8 layers, 8 heads, ff 1024; one model call per sampling step, no guidance, as MotionDiffuse
samples), on a HumanML3D-like batch (default batch 64, 196 frames, valid lengths drawn in 40..196
with a fixed seed, cached text features — no CLIP) it times, dense and at every reduction rate, in
the same process and interleaved (every repeat runs every variant in turn, so machine load hits
all alike):

* ``train`` — one training step: ``SimpleDiffusion.training_losses`` with the sparse diffusion
  wrapper (keyframe selection on x0 + mask noise included) + backward + ``AdamW.step``;
* ``sample`` — one sampling step (MDM: classifier-free guidance, two forward passes; ``eval``,
  ``no_grad``) at a late step (``t < round(γT)``, dynamic update forced on: VW on x_t, the
  costliest step of the schedule);
* ``loop`` — the whole sampling loop a user runs: ``--steps`` steps (MDM: with classifier-free
  guidance) and the config's own schedule;

plus, for the sparse variants, the share of the step spent in keyframe selection and in the
interpolation back to all frames, and peak memory (CUDA: max allocated; CPU: the peak rise of the
process RSS), and each cell's kernel launches (:func:`launches`). ``--amp bf16`` runs under
``torch.autocast``; ``--compile MODE [MODE ...]`` compiles dense and sparse models alike with each
mode (the helper of ``--sparse_compile``, docs/compile.md; default on CUDA: eager and
reduce-overhead, one table; speed-ups against the dense model at the same mode). Medians of
``--repeats`` after ``--warmup`` runs (compilation happens in the warm-up). The table names the
device, the mode and the attention backend the sparse model ran.

``smdm bench keyframes`` times VW selection alone on ``[64, 196, 64]``.
"""
from __future__ import annotations

import argparse
import contextlib
import ctypes
import os
import statistics
import sys
import threading
import time
import warnings
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import torch

from ..adapters.state import sparse_config_of
from ..core.config import BACKENDS
from ..integrations.compile import COMPILE_MODES
from ..core.registry import Registry
from .common.args import add_common_flags, add_overwrite, float_range, int_range, note_printer, progress_of, resolve_device

TARGETS = {"train": 4.0, "sample": 3.5, "loop": 3.0, "overhead": 0.10}  # at 80% reduction
MODES = ("train", "sample", "loop")


# ----------------------------------------------------------------------------------------- utils
def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _pin_malloc() -> bool:
    """Fix glibc's mmap threshold at 1 MiB so that big freed tensors are unmapped at once (RSS then
    follows the live tensors; without this the dynamic threshold keeps them in the heap)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
        ok = libc.mallopt(M_MMAP_THRESHOLD, 1 << 20) == 1
        libc.mallopt(M_TRIM_THRESHOLD, 1 << 20)
        return ok
    except Exception:
        return False


def _rss_bytes() -> int:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except Exception:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


class PeakMemory:
    """Context manager: peak memory rise (bytes) during the block."""

    def __init__(self, device: torch.device, interval: float = 0.002) -> None:
        self.device, self.interval, self.peak = device, interval, 0

    def __enter__(self) -> "PeakMemory":
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self.base = torch.cuda.memory_allocated(self.device)
            return self
        self.base = _rss_bytes()
        self._max = self.base
        self._stop = threading.Event()

        def poll() -> None:
            while not self._stop.is_set():
                self._max = max(self._max, _rss_bytes())
                time.sleep(self.interval)

        self._thread = threading.Thread(target=poll, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
            self.peak = torch.cuda.max_memory_allocated(self.device) - self.base
            return
        self._max = max(self._max, _rss_bytes())
        self._stop.set()
        self._thread.join()
        self.peak = self._max - self.base


def time_it(fn: Callable[[], Any], device: torch.device, repeats: int, warmup: int) -> List[float]:
    for _ in range(warmup):
        fn()
    _sync(device)
    out = []
    for _ in range(repeats):
        _sync(device)
        t0 = time.perf_counter()
        fn()
        _sync(device)
        out.append(time.perf_counter() - t0)
    return out


# ----------------------------------------------------------------------------------------- setup
def mdm_size(quick: bool = False) -> Dict[str, int]:
    if quick:
        return dict(latent_dim=64, ff_size=128, num_layers=2, num_heads=4)
    return dict(latent_dim=512, ff_size=1024, num_layers=8, num_heads=4)


def make_batch(batch: int, frames: int, device: torch.device, seed: int = 0, min_len: int = 40
               ) -> Dict[str, Any]:
    """A HumanML3D-like batch: normal features ``[B, 263, 1, N]``, lengths in ``min_len..N``."""
    g = torch.Generator().manual_seed(seed)
    lengths = _lengths(batch, frames, min_len, g)
    x = torch.randn(batch, 263, 1, frames, generator=g)
    valid = torch.arange(frames) < lengths[:, None]
    x = x * valid.view(batch, 1, 1, frames)
    y = {"mask": valid.view(batch, 1, 1, frames).to(device), "lengths": lengths.to(device),
         "text_embed": torch.randn(1, batch, 512, generator=g).to(device)}
    return {"x": x.to(device), "y": y, "lengths": lengths}


def _lengths(batch: int, frames: int, min_len: int, g: torch.Generator) -> torch.Tensor:
    """``[B]`` long valid lengths drawn in ``min_len..frames``; the first is ``frames`` (the longest
    sample sets the padded length)."""
    lengths = torch.randint(min(min_len, frames), frames + 1, (batch,), generator=g)
    lengths[0] = frames
    return lengths


FSQ_CHOICES = {"paper": "sparse only (dense = upstream MDM, sparse = the paper's recipe)",
               "both": "dense and sparse (like with like)", "off": "neither"}


class Workload:
    """How the benchmark builds, feeds and calls the in-package model of one registered model
    family (:data:`~smdm_plugin.adapters.families.FAMILIES`). One subclass per family, registered in
    :data:`WORKLOADS` under the family's name; ``--family`` offers the registered families that
    have one. The sparse model is made with ``sparsify(..., family=name)``."""

    #: the model family's registered name
    family: str = ""
    #: the variants ``--arch`` chooses among (the first ones by default)
    archs: Tuple[str, ...] = ()
    #: whether FSQ-quantised attention keys apply (softmax attention)
    fsq: bool = True
    #: model calls per sampling step (2: classifier-free guidance)
    passes: int = 1

    def size(self, quick: bool) -> Dict[str, int]:
        raise NotImplementedError

    def model(self, arch: str, quick: bool, frames: int, root: Optional[str] = None) -> torch.nn.Module:
        """The dense model; ``root``: an upstream checkout to take the model class from (None =
        the in-package one)."""
        raise NotImplementedError

    def source(self, root: Optional[str]) -> str:
        """Where the model class comes from, as the table names it."""
        return "in-package"

    #: the environment variable naming an upstream checkout (None: no upstream model to load)
    root_env: Optional[str] = None

    def check_root(self, root: str) -> None:
        """Raise ``ValueError`` (starting ``--root:``) unless ``root`` is a usable checkout."""
        raise ValueError(f"--root: --family {self.family} has no upstream model to load (leave it out)")

    def batch(self, batch: int, frames: int, device: torch.device, quick: bool) -> Dict[str, Any]:
        """``{"x": the motion as the model takes it, "frames": [B, N, D], "lengths": [B] (CPU),
        "kwargs": the model's keyword arguments}``."""
        raise NotImplementedError

    def kwargs(self, data: Dict[str, Any]) -> Dict[str, Any]:
        """A fresh copy of the model keyword arguments (hooks may add keys to them)."""
        return dict(data["kwargs"])

    def denoiser(self, model: torch.nn.Module) -> torch.nn.Module:
        """What one sampling step calls: ``denoiser(x_t, t, **kwargs)``."""
        return model.eval()

    def call_args(self, data: Dict[str, Any], mask: torch.Tensor, capacity: int) -> Tuple[tuple, Dict[str, Any]]:
        """``(args, kwargs)`` of a model call with the given keyframes, as the family's ``read_call``
        reads them."""
        raise NotImplementedError

    def lead(self, model: torch.nn.Module) -> int:
        """Tokens before the frames in the keyframe transformer's sequence."""
        return 0

    def backend(self, backend: str, device: torch.device, compile_mode: str) -> str:
        """The sparse model's attention, as the table names it."""
        from ..core.attention_backends import resolve_backend_name

        return resolve_backend_name(backend, device) if compile_mode == "none" else "compact"


class MDMWorkload(Workload):
    """``TinyMDM`` at MDM's HumanML3D size, ``trans_enc`` / ``trans_dec``; cached text embeddings;
    sampling with classifier-free guidance (two passes per step) as MDM samples."""

    family, archs, fsq, passes = "mdm", ("trans_enc", "trans_dec"), True, 2

    def size(self, quick: bool) -> Dict[str, int]:
        return mdm_size(quick)

    def model(self, arch: str, quick: bool, frames: int, root: Optional[str] = None) -> torch.nn.Module:
        from ..reference.backbone import TinyMDM

        return TinyMDM(arch=arch, **mdm_size(quick))

    def source(self, root: Optional[str]) -> str:
        return "in-package TinyMDM"

    def batch(self, batch: int, frames: int, device: torch.device, quick: bool) -> Dict[str, Any]:
        from ..adapters.mdm import frames_layout

        data = make_batch(batch, frames, device)
        return {**data, "frames": frames_layout(data["x"]), "kwargs": {"y": data["y"]}}

    def kwargs(self, data: Dict[str, Any]) -> Dict[str, Any]:
        return {"y": dict(data["y"])}

    def denoiser(self, model: torch.nn.Module) -> torch.nn.Module:
        from ..reference.diffusion import ClassifierFreeGuidance

        return ClassifierFreeGuidance(model.eval(), scale=2.5)

    def call_args(self, data, mask, capacity):
        from ..adapters.request import with_request

        return (data["x"], None, with_request(data["y"], mask=mask, capacity=capacity)), {}

    def lead(self, model: torch.nn.Module) -> int:
        return 1 if model.arch == "trans_enc" or getattr(model, "emb_trans_dec", False) else 0


class MotionDiffuseWorkload(Workload):
    """MotionDiffuse's denoiser layout (:class:`~smdm_plugin.reference.motiondiffuse_denoiser.MotionDiffuseDenoiser`,
    latent 512, 8 layers, 8 heads, FFN 1024) on ``[B, N, 263]``; precomputed text features
    (``xf_proj``, ``xf_out`` of 77 tokens) as MotionDiffuse computes them once per prompt; one
    model call per sampling step (MotionDiffuse samples without guidance). Its self-attention is
    linear: no FSQ keys, no attention backend (the sparse model runs its own blocks on the K slots)."""

    family, archs, fsq, passes = "motiondiffuse", ("motiondiffuse",), False, 1

    def size(self, quick: bool) -> Dict[str, int]:
        from ..reference.motiondiffuse_denoiser import motiondiffuse_size

        return motiondiffuse_size(quick)

    root_env = "SMDM_MOTIONDIFFUSE_ROOT"

    def check_root(self, root: str) -> None:
        upstream_motion_transformer(root)

    def model(self, arch: str, quick: bool, frames: int, root: Optional[str] = None) -> torch.nn.Module:
        from ..reference.motiondiffuse_denoiser import MotionDiffuseDenoiser

        cls = MotionDiffuseDenoiser if root is None else upstream_motion_transformer(root)
        return cls(input_feats=263, num_frames=max(196, frames), **self.size(quick))

    def source(self, root: Optional[str]) -> str:
        return ("in-package MotionDiffuseDenoiser (MotionDiffuse's interface)" if root is None
                else f"upstream MotionDiffuse {root}")

    def batch(self, batch: int, frames: int, device: torch.device, quick: bool) -> Dict[str, Any]:
        size = self.size(quick)
        g = torch.Generator().manual_seed(0)
        lengths = _lengths(batch, frames, 40, g)
        x = torch.randn(batch, frames, 263, generator=g) * (torch.arange(frames) < lengths[:, None])[..., None]
        kw = {"length": lengths.to(device),
              "xf_proj": torch.randn(batch, 4 * size["latent_dim"], generator=g).to(device),
              "xf_out": torch.randn(batch, 77, size["text_latent_dim"], generator=g).to(device)}
        return {"x": x.to(device), "frames": x.to(device), "lengths": lengths, "kwargs": kw}

    def call_args(self, data, mask, capacity):
        from ..adapters.request import with_request

        return (data["x"], None, data["kwargs"]["length"]), with_request({}, "model_kwargs", mask=mask, capacity=capacity)

    def backend(self, backend: str, device: torch.device, compile_mode: str) -> str:
        return "n/a (linear attention)"


def upstream_motion_transformer(root: str) -> type:
    """MotionDiffuse's own ``MotionTransformer`` class from the checkout ``root`` (the folder
    holding ``text2motion/``). Raises ``ValueError`` naming ``root`` when it is not one or cannot be
    imported (MotionDiffuse needs ``openai-clip`` and CLIP's weights)."""
    import importlib

    t2m = os.path.join(os.path.abspath(root), "text2motion")
    if not os.path.isfile(os.path.join(t2m, "models", "transformer.py")):
        raise ValueError(f"--root: {root} is not a MotionDiffuse checkout (no text2motion/models/transformer.py)")
    if t2m not in sys.path:
        sys.path.insert(0, t2m)
    try:
        return importlib.import_module("models.transformer").MotionTransformer
    except Exception as e:  # noqa: BLE001 - any import failure is the checkout's, said in one line
        raise ValueError(f"--root: cannot import MotionDiffuse's models.transformer from {t2m}: "
                         f"{type(e).__name__}: {e}") from None


#: the benchmark's workload per model family name
WORKLOADS: Registry[Workload] = Registry("benchmark workload")
for _w in (MDMWorkload(), MotionDiffuseWorkload()):
    WORKLOADS.register(_w.family, _w)


def family_choices() -> List[str]:
    """The registered model families the benchmark can time (those with a :class:`Workload`)."""
    from ..adapters.families import FAMILIES

    return [n for n in FAMILIES.names() if n in WORKLOADS]


def build(arch: str, reduction: Optional[float], device: torch.device, quick: bool, steps: int,
          backend: str = "auto", seed: int = 0, fsq: str = "paper", family: str = "mdm", frames: int = 196,
          root: Optional[str] = None, **sparse: Any):
    """(model, diffusion) of ``family``'s workload — dense when ``reduction`` is None. ``fsq``
    (:data:`FSQ_CHOICES`): which side gets FSQ-quantised attention keys (families whose attention
    has softmax keys). ``root``: an upstream checkout whose model class to use."""
    from ..adapters.surgery import sparsify
    from ..core.config import SparseConfig
    from ..core.fsq import quantize_attention_keys
    from ..reference.diffusion import SimpleDiffusion

    work = WORKLOADS.get(family)
    fsq = fsq if work.fsq else "off"
    torch.manual_seed(seed)
    model = work.model(arch, quick, frames, root).to(device)
    diffusion = SimpleDiffusion(steps)
    if reduction is not None:
        sparsify(model, SparseConfig(reduction=reduction, attention_backend=backend, fsq=fsq != "off", **sparse),
                 diffusion=diffusion, family=family)
    elif fsq == "both":
        quantize_attention_keys(model, SparseConfig().fsq_levels)
    return model, diffusion


def _autocast(device: torch.device, amp: str):
    if amp == "bf16":
        return torch.autocast(device_type=device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def _compiled(model: torch.nn.Module, compile_mode: str) -> torch.nn.Module:
    """``model`` compiled in place by the helper every integration uses (``--sparse_compile``,
    ``smdm train --compile``; docs/compile.md): the denoiser, guidance wrapper around it eager."""
    from ..integrations.compile import compile_model

    if compile_mode != "none":
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")        # reduce-overhead off CUDA: stated in the table instead
            compile_model(model, compile_mode)
    return model


def _applied(model: torch.nn.Module) -> str:
    """How ``model`` ran: ``eager`` or the compile mode that applied (reduce-overhead falls back to
    default without CUDA)."""
    from ..integrations.compile import compile_setting

    s = compile_setting(model)
    return "eager" if s is None else s.mode


#: host-side launch calls the CUDA profiler records (a CUDA graph replay is one cudaGraphLaunch)
_CUDA_LAUNCH_CALLS = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx",
                      "cudaGraphLaunch", "cudaLaunchCooperativeKernel")


def launches(fn: Callable[[], None], device: torch.device, compiled: bool) -> Optional[int]:
    """Kernel launches of one call of ``fn`` (already warmed up). Eager: counted as CUDA runs them
    (:mod:`smdm_plugin.core.launches`, on any device). Compiled: on CUDA the launch calls the
    profiler records (a CUDA graph replay counts once); elsewhere None (a compiler's fused kernels
    bypass the dispatcher: nothing CUDA-equivalent to count)."""
    if not compiled:
        from ..core.launches import count_launches

        return count_launches(fn, warmup=0).count
    if device.type != "cuda":
        return None
    try:
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            fn()
            torch.cuda.synchronize(device)
        return int(sum(e.count for e in prof.key_averages() if e.key in _CUDA_LAUNCH_CALLS))
    except Exception:  # a profiler that cannot run here: say so in the table, never fail the bench
        return None


def _train_step_fn(work: Workload, model, diffusion, batch, device, amp: str, compile_mode: str, seed: int = 0
                   ) -> Callable[[], None]:
    model.train()
    run = _compiled(model, compile_mode)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    g = torch.Generator(device="cpu").manual_seed(seed)
    B = batch["x"].shape[0]
    ts = [torch.randint(0, diffusion.num_timesteps, (B,), generator=g).to(device) for _ in range(16)]
    step_no = [0]

    def step() -> None:
        t = ts[step_no[0] % len(ts)]                 # made ahead of time: no host-to-device copy
        step_no[0] += 1
        with _autocast(device, amp):
            loss = diffusion.training_losses(run, batch["x"], t, work.kwargs(batch))["loss"].mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step


def _sample_step_fn(work: Workload, model, diffusion, batch, device, amp: str, compile_mode: str
                    ) -> Callable[[], None]:
    den = work.denoiser(_compiled(model, compile_mode))
    B = batch["x"].shape[0]
    from ..core.schedule import MaskSchedule

    config = sparse_config_of(model)  # the public accessor, not the model's private state
    late = MaskSchedule(config).late_steps if config is not None else 1
    t = torch.full((B,), max(0, late - 1), dtype=torch.long, device=device)
    x_t = diffusion.q_sample(batch["x"], t)

    def step() -> None:
        with torch.no_grad(), _autocast(device, amp):
            x_t.add_(0)                              # a new x_t every time
            den(x_t, t, **work.kwargs(batch))

    return step


def _sample_loop_fn(work: Workload, model, diffusion, batch, device, amp: str, compile_mode: str
                    ) -> Callable[[], None]:
    den = work.denoiser(_compiled(model, compile_mode))
    shape = tuple(batch["x"].shape)
    g = torch.Generator(device=device).manual_seed(0)

    def loop() -> None:
        with torch.no_grad(), _autocast(device, amp):
            diffusion.p_sample_loop(den, shape, work.kwargs(batch), device=device, generator=g)

    return loop


def _overhead_fns(work: Workload, model, batch, device, train: bool):
    """Keyframe selection and the interpolation back to all frames, alone, with the step's
    shapes: ``(select, interp)`` callables."""
    from ..adapters.diffusion import model_noise
    from ..adapters.state import get_state
    from ..core.fill import fill_frames

    state = get_state(model)
    frames = batch["frames"]
    lengths = batch["lengths"].to(device)
    B, N = frames.shape[:2]
    if train:
        def select():
            return state.schedule.training_mask(frames, lengths, None, model_noise(model), checked=True)
    else:
        late = torch.zeros(B, dtype=torch.long, device=device)

        def select():
            return state.schedule.sampling_mask(frames, late, lengths, checked=True)
    args, kwargs = work.call_args(batch, select(), state.schedule.capacity(N, training=train))
    plan = state.family.read_call(state, args, kwargs).plan(state)
    lead = work.lead(model)
    K = plan.capacity
    width = getattr(model, "latent_dim")
    h = torch.randn((lead + K) * B, width, device=device, requires_grad=train)
    rows = torch.arange((lead + K) * B, device=device).view(lead + K, B)

    def interp():
        if train:
            fill_frames(h, rows, plan, lead).sum().backward()
        else:
            with torch.no_grad():
                fill_frames(h, rows, plan, lead)

    return select, interp


# ----------------------------------------------------------------------------------------- run
def run_bench(archs: Optional[Sequence[str]] = None, reductions: Sequence[float] = (0.6, 0.7, 0.8, 0.9),
              batch: int = 64, frames: int = 196, repeats: int = 3, warmup: int = 1, device: str = "auto",
              quick: bool = False, backend: str = "auto", steps: int = 50, fastpath: bool = False,
              modes: Sequence[str] = ("train", "sample"), amp: str = "fp32", compile_mode: Any = "none",
              progress: Optional[Callable[[str], None]] = None, fsq: str = "paper", family: str = "mdm",
              root: Optional[str] = None) -> Dict[str, Any]:
    """Dense and sparse, interleaved per repeat; wall-clock, process CPU time, peak memory.
    ``family``: a registered model family with a :class:`Workload` (:func:`family_choices`);
    ``archs``: its variants (None = all of them); ``root``: an upstream checkout whose model class
    to time (None = the in-package one)."""
    work = WORKLOADS.get(family)
    archs = list(work.archs if archs is None else archs)
    bad = [a for a in archs if a not in work.archs]
    if bad:
        raise ValueError(f"run_bench: arch {bad[0]!r} is not a {family} variant; expected one of {list(work.archs)}")
    mha = getattr(torch.backends, "mha", None)
    has_fp = mha is not None and hasattr(mha, "set_fastpath_enabled")
    before = mha.get_fastpath_enabled() if has_fp else None
    if has_fp:
        mha.set_fastpath_enabled(bool(fastpath))
    try:
        return _run_bench(work, archs, list(reductions), batch, frames, repeats, warmup, device, quick, backend,
                          steps, fastpath, list(modes), amp, compile_mode, progress, fsq if work.fsq else "off", root)
    finally:
        if has_fp:
            mha.set_fastpath_enabled(before)


def _run_bench(work: Workload, archs, reductions, batch, frames, repeats, warmup, device, quick, backend, steps, fastpath,
               modes, amp, compile_mode, progress, fsq, root) -> Dict[str, Any]:
    dev = resolve_device(device)
    if dev.type == "cpu":
        _pin_malloc()
    data = work.batch(batch, frames, dev, quick)
    say = progress or (lambda s: None)
    rows: List[Dict[str, Any]] = []
    variants: List[Optional[float]] = [None] + list(reductions)
    makers = {"train": _train_step_fn, "sample": _sample_step_fn, "loop": _sample_loop_fn}
    compile_modes = compile_modes_of(compile_mode)
    for arch in archs:
        for mode in modes:
            sparse_kw = {"dynamic_update": True} if mode == "sample" else {}
            cells = []
            for cmode in compile_modes:                # dense and sparse at each compile mode: one table
                for red in variants:
                    model, diffusion = build(arch, red, dev, quick, steps, backend, fsq=fsq, family=work.family,
                                             frames=frames, root=root, **sparse_kw)
                    fn = makers[mode](work, model, diffusion, data, dev, amp, cmode)
                    cells.append({"red": red, "model": model, "fn": fn, "wall": [], "cpu": [], "mem": 0,
                                  "compile": cmode})
            for _ in range(warmup):
                for c in cells:
                    c["fn"]()
            for _ in range(repeats):
                for c in cells:
                    with PeakMemory(dev) as mem:
                        _sync(dev)
                        w0, c0 = time.perf_counter(), time.process_time()
                        c["fn"]()
                        _sync(dev)
                        c["wall"].append(time.perf_counter() - w0)
                        c["cpu"].append(time.process_time() - c0)
                    c["mem"] = max(c["mem"], mem.peak)
            for c in cells:
                c["launches"] = launches(c["fn"], dev, c["compile"] != "none")
            for c in cells:
                dense = next(d for d in cells if d["red"] is None and d["compile"] == c["compile"])
                d_wall, d_cpu = statistics.median(dense["wall"]), statistics.median(dense["cpu"])
                red, wall, cpu = c["red"], statistics.median(c["wall"]), statistics.median(c["cpu"])
                row: Dict[str, Any] = {
                    "family": work.family, "arch": arch, "mode": mode, "reduction": 0.0 if red is None else red,
                    "compile": c["compile"], "compile_applied": _applied(c["model"]), "launches": c["launches"],
                    "sparse_backend": work.backend(backend, dev, c["compile"]),
                    "variant": "dense" if red is None else f"sparse {int(round(red * 100))}%",
                    "median_s": wall, "cpu_s": cpu, "times_s": c["wall"], "cpu_times_s": c["cpu"],
                    "speedup": d_wall / wall, "cpu_speedup": d_cpu / cpu, "peak_mem_mib": c["mem"] / 2 ** 20,
                    "mem_ratio": c["mem"] / dense["mem"] if dense["mem"] > 0 else None,
                }
                if red is not None and mode != "loop":
                    sel, interp = _overhead_fns(work, c["model"], data, dev, mode == "train")
                    with _autocast(dev, amp):
                        t_sel = statistics.median(time_it(sel, dev, repeats, 1))
                        t_int = statistics.median(time_it(interp, dev, repeats, 1))
                    n_sel = n_int = 1 if mode == "train" else work.passes   # CFG: two passes, two selections
                    row.update(select_s=t_sel * n_sel, interp_s=t_int * n_int,
                               overhead_share=(t_sel * n_sel + t_int * n_int) / wall)
                rows.append(row)
                say(_row_line(row))
            del cells
    return {
        "family": work.family, "model_source": work.source(root), "device": str(dev), "device_name": _device_name(dev), "torch": torch.__version__,
        "threads": torch.get_num_threads(), "batch": batch, "frames": frames,
        "lengths": [int(v) for v in data["lengths"]], "model": work.size(quick), "quick": bool(quick), "repeats": repeats,
        "warmup": warmup, "backend": backend,
        "sparse_backend": " / ".join(dict.fromkeys(work.backend(backend, dev, m) for m in compile_modes)), "amp": amp,
        "compile": ", ".join(compile_modes), "compile_modes": compile_modes, "fastpath": bool(fastpath), "diffusion_steps": steps, "fsq": fsq,
        "load_average": _loadavg(), "rows": rows, "targets": TARGETS,
    }


def compile_modes_of(compile_mode: Any) -> List[str]:
    """``--compile``'s modes as a list (one mode or several; each checked, duplicates dropped)."""
    from ..integrations.compile import check_compile_mode

    modes = [compile_mode] if isinstance(compile_mode, str) else list(compile_mode)
    if not modes:
        raise ValueError("run_bench: compile_mode: give at least one of none, default, reduce-overhead")
    return list(dict.fromkeys(check_compile_mode(m, "--compile") for m in modes))


def _loadavg() -> Optional[List[float]]:
    try:
        return [round(v, 2) for v in os.getloadavg()]
    except OSError:
        return None


def _device_name(dev: torch.device) -> str:
    if dev.type == "cuda":
        return torch.cuda.get_device_name(dev)
    import platform

    return f"{platform.processor() or platform.machine()} ({os.cpu_count()} cores)"


def _launch_cell(r: Dict[str, Any]) -> str:
    return "—" if r.get("launches") is None else str(r["launches"])


def _row_line(r: Dict[str, Any]) -> str:
    ov = f" overhead {100 * r['overhead_share']:.1f}%" if "overhead_share" in r else ""
    return (f"{r['arch']} {r['mode']:6s} {r.get('compile_applied', 'eager'):15s} {r['variant']:10s} "
            f"{r['median_s'] * 1000:9.1f} ms {_launch_cell(r):>6s} launches "
            f"x{r['speedup']:.2f} (cpu x{r['cpu_speedup']:.2f}){ov}")


def _fsq_note(result: Dict[str, Any]) -> str:
    fam = result.get("family", "mdm")
    if fam in WORKLOADS and not WORKLOADS.get(fam).fsq:
        return "n/a (no softmax attention keys)"
    return FSQ_CHOICES[result.get("fsq", "paper")]


def _compile_label(mode: str) -> str:
    return "eager" if mode in ("none", "eager") else f"torch.compile {mode}"


def markdown(result: Dict[str, Any]) -> str:
    modes = result.get("compile_modes") or [result["compile"]]
    mode = f"{result['amp']}, " + " and ".join(_compile_label(m) for m in modes)
    lines = [f"device: {result['device_name']} ({result['device']}), torch {result['torch']}, "
             f"{result['threads']} threads; {mode}; sparse attention backend: {result['sparse_backend']}; "
             f"FSQ keys: {_fsq_note(result)}; model family: {result.get('family', 'mdm')} "
             f"({result.get('model_source', 'in-package')}); "
             f"batch {result['batch']}, {result['frames']} frames, model {result['model']}, "
             f"T = {result['diffusion_steps']}; median of {result['repeats']} (dense and sparse interleaved) "
             f"after {result['warmup']} warm-up; load average {result.get('load_average')}",
             "",
             "| arch | step | compile | variant | wall (ms) | launches | speed-up | CPU time (ms) | speed-up (CPU) | "
             "selection (ms) | interpolation (ms) | overhead share | peak mem (MiB) | mem vs dense |",
             "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in result["rows"]:
        sel = f"{r['select_s'] * 1000:.1f}" if "select_s" in r else "—"
        itp = f"{r['interp_s'] * 1000:.1f}" if "interp_s" in r else "—"
        ov = f"{100 * r['overhead_share']:.1f}%" if "overhead_share" in r else "—"
        mr = ("—" if r["variant"] == "dense" or r.get("mem_ratio") is None or result.get("quick")
              else f"{r['mem_ratio']:.2f}")
        applied = r.get("compile_applied", "eager")
        cm = _compile_label(applied) + (f" (asked {r['compile']})" if r.get("compile", "none") not in
                                        ("none", applied) else "")
        lines.append(f"| {r['arch']} | {r['mode']} | {cm} | {r['variant']} | {r['median_s'] * 1000:.1f} | "
                     f"{_launch_cell(r)} | {r['speedup']:.2f}× | {r['cpu_s'] * 1000:.1f} | {r['cpu_speedup']:.2f}× | "
                     f"{sel} | {itp} | {ov} | {r['peak_mem_mib']:.0f} | {mr} |")
    lines += ["", "launches: kernel launches of the timed call, counted as CUDA runs them (smdm_plugin.core.launches; "
              "eager cells, any device: off CUDA the sparse model's own CPU path, which packs keyframes; a GPU runs "
              "the static-shape path); compiled cells: on CUDA the launch calls the profiler records (a CUDA "
              "graph replay counts once), elsewhere — (a compiler's fused kernels bypass the dispatcher). "
              "Speed-ups are against the dense model at the same compile mode."]
    at = [r for r in result["rows"] if abs(r["reduction"] - 0.8) < 1e-9]
    if result.get("quick"):  # a smoke test: fixed costs dominate at this size, so targets would mislead
        lines += ["", "--quick: a tiny model and batch, to check that the benchmark runs. At this size fixed "
                  "costs (Python, selection, kernel launches) dominate, so the speed-ups say nothing about the "
                  "full-size model, and the targets and memory ratios are left out. For real numbers run "
                  f"`smdm bench --family {result.get('family', 'mdm')}` (full size, batch 64, 196 frames; "
                  "minutes on a CPU) or add `--device cuda`."]
    elif at:
        lines += ["", "at 80% reduction (targets: training ≥ 4×, sampling step ≥ 3.5×, sampling loop ≥ 3×, "
                  "selection + interpolation < 10% of the sparse step):"]
        for r in at:
            tgt = TARGETS[r["mode"]]
            ov = ""
            if "overhead_share" in r:
                ov = (f"; overhead {100 * r['overhead_share']:.1f}% "
                      f"{'met' if r['overhead_share'] < TARGETS['overhead'] else 'MISSED'}")
            lines.append(f"* {r['arch']} {r['mode']}: {r['speedup']:.2f}× (target {tgt}×) "
                         f"{'met' if r['speedup'] >= tgt else 'MISSED'}{ov}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------- keyframes
def bench_keyframes(batch: int = 64, frames: int = 196, dims: int = 64, reduction: float = 0.8,
                    repeats: int = 5, device: str = "auto") -> Dict[str, Any]:
    """VW selection (the fused op) on ``[batch, frames, dims]`` (random-walk features, full lengths)."""
    from ..core.selection import select_keyframes

    dev = resolve_device(device)
    g = torch.Generator().manual_seed(0)
    feats = torch.randn(batch, frames, dims, generator=g).cumsum(1).to(dev)
    times = time_it(lambda: select_keyframes(feats, None, reduction, "vw"), dev, repeats, 1)
    return {"shape": [batch, frames, dims], "reduction": reduction, "device": str(dev),
            "median_s": statistics.median(times), "times_s": times}


# ----------------------------------------------------------------------------------------- CLI
QUICK = {"batch": 4, "frames": 60, "repeats": 1, "warmup": 0}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--family", default="mdm", choices=family_choices(),
                   help="model family to time, on its in-package model: mdm (TinyMDM at MDM's size), "
                        "motiondiffuse (MotionDiffuse's MotionTransformer layout); default mdm")
    p.add_argument("--root", default=None,
                   help="--family motiondiffuse: a MotionDiffuse checkout (the folder holding text2motion/) whose "
                        f"own MotionTransformer to time (default ${MotionDiffuseWorkload.root_env} when set, else "
                        "the in-package one with the same layout)")
    p.add_argument("--arch", nargs="+", default=None, choices=["trans_enc", "trans_dec"],
                   help="MDM architectures to time (default: both; --family mdm only)")
    p.add_argument("--reductions", nargs="+", type=float_range(0.0, 1.0, hi_open=True), default=[0.6, 0.7, 0.8, 0.9],
                   help="fractions of frames dropped, each in [0, 1)")
    p.add_argument("--batch", type=int_range(1), default=None, help="motions per batch (default 64)")
    p.add_argument("--frames", type=int_range(2), default=None, help="frames per motion (default 196)")
    p.add_argument("--repeats", type=int_range(1), default=None, help="timed runs per cell, median reported (default 3)")
    p.add_argument("--warmup", type=int_range(0), default=None, help="untimed runs before timing (default 1)")
    p.add_argument("--backend", default="auto", choices=BACKENDS,
                   help="keyframe attention backend of the sparse model")
    p.add_argument("--modes", nargs="+", default=["train", "sample"], choices=list(MODES),
                   help="train: one training step; sample: one CFG sampling step (VW on x_t); "
                        "loop: the whole T-step CFG sampling loop")
    p.add_argument("--steps", type=int_range(1), default=50, help="diffusion steps T (default 50, the paper's recipe)")
    p.add_argument("--amp", choices=["fp32", "bf16"], default="fp32", help="bf16: torch.autocast for both")
    p.add_argument("--fsq", choices=list(FSQ_CHOICES), default=None,
                   help="FSQ attention keys on: " + "; ".join(f"{k}: {v}" for k, v in FSQ_CHOICES.items())
                        + " (default paper; --family mdm only: MotionDiffuse's attention is linear)")
    p.add_argument("--compile", dest="compile_mode", nargs="+", default=None, choices=list(COMPILE_MODES),
                   metavar="MODE",
                   help="torch.compile dense and sparse models alike with each mode, one table: none (eager), default, "
                        "reduce-overhead (CUDA graphs; CUDA only, else default) — the helper of --sparse_compile "
                        "(docs/compile.md). Default: none reduce-overhead on CUDA, none elsewhere")
    p.add_argument("--fastpath", action="store_true",
                   help="leave torch's MHA/Transformer fast path enabled (default: off for dense and sparse)")
    p.add_argument("--quick", action="store_true",
                   help=f"a smoke run: tiny model; batch, frames, repeats and warm-up default to {QUICK} "
                        "(values you pass win)")
    p.add_argument("--out", default=None, help="write the result as <out>.json and the table as <out>.md")
    add_overwrite(p)
    add_common_flags(p)  # --no-progress: no per-cell lines on stderr


def busy_note(threads: int) -> Optional[str]:
    """A warning when other processes already keep the CPU busy (timings with several threads per
    process then suffer badly from oversubscription: threads wait on preempted partners)."""
    load = _loadavg()
    cores = os.cpu_count() or 1
    if load and threads > 1 and load[0] > cores:
        return (f"note: load average {load[0]:.1f} on {cores} cores — other jobs are running; "
                f"{threads} threads per process will be slowed by oversubscription, consider --threads 1")
    return None


def output_paths(out: str):
    """``(json, md)`` for ``--out`` (``x``, ``x.json`` or ``x.md`` all give ``x.json`` + ``x.md``)."""
    base, ext = os.path.splitext(out)
    base = base if ext.lower() in (".json", ".md") else out
    return base + ".json", base + ".md"


def main_bench(args: argparse.Namespace, parser: argparse.ArgumentParser) -> Dict[str, Any]:
    from ..io.files import OutputExistsError, atomic_write_json, atomic_write_text, check_new_file

    work = WORKLOADS.get(args.family)
    bad = [a for a in args.arch or () if a not in work.archs]
    if bad:
        parser.error(f"argument --arch: {bad[0]!r} is an MDM architecture; --family {args.family} has no "
                     "--arch choice (leave it out)")
    if args.fsq not in (None, "off") and not work.fsq:
        parser.error(f"argument --fsq: --family {args.family} has no softmax attention keys to quantise "
                     "(linear attention); leave --fsq out")
    args.fsq = args.fsq or ("paper" if work.fsq else "off")
    root = args.root if args.root is not None else (os.environ.get(work.root_env) or None if work.root_env else None)
    if root is not None:
        try:
            work.check_root(root)
        except ValueError as e:
            parser.error(str(e).replace("--root:", "argument --root:", 1))
    defaults = QUICK if args.quick else {"batch": 64, "frames": 196, "repeats": 3, "warmup": 1}
    for k, v in defaults.items():
        if getattr(args, k) is None:
            setattr(args, k, v)
    paths = None
    if args.out:
        paths = output_paths(args.out)
        try:
            for p in paths:
                check_new_file(p, args.overwrite, "smdm bench: --out")
        except OutputExistsError as e:
            parser.error(str(e))
    if args.compile_mode is None:
        args.compile_mode = ["none", "reduce-overhead"] if resolve_device(args.device).type == "cuda" else ["none"]
    from .common.threads import apply_threads
    apply_threads(args.threads)
    note = busy_note(torch.get_num_threads()) if resolve_device(args.device).type == "cpu" else None
    say = note_printer(args)
    if note:
        say(note, file=sys.stderr)
    result = run_bench(args.arch, args.reductions, args.batch, args.frames, args.repeats, args.warmup, args.device,
                       args.quick, args.backend, args.steps, args.fastpath, args.modes, args.amp, args.compile_mode,
                       progress=(lambda s: print(s, file=sys.stderr, flush=True)) if progress_of(args) else None,
                       fsq=args.fsq, family=args.family, root=root)
    table = markdown(result)
    print(table)
    if paths:
        atomic_write_json(paths[0], result)
        atomic_write_text(paths[1], table + "\n")
        say(f"\nwrote {paths[0]} and {paths[1]}")
    return result


def main(argv: Optional[List[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "keyframes":
        p = argparse.ArgumentParser(prog="smdm bench keyframes", description="time VW keyframe selection")
        p.add_argument("--batch", type=int_range(1), default=64, help="motions per call (default 64)")
        p.add_argument("--frames", type=int_range(2), default=196, help="frames per motion (default 196)")
        p.add_argument("--dims", type=int_range(1), default=64,
                       help="selection features per frame (default 64: 21 joints x 3 + frame index)")
        p.add_argument("--reduction", type=float_range(0.0, 1.0, hi_open=True), default=0.8,
                       help="fraction of frames dropped, in [0, 1) (default 0.8)")
        p.add_argument("--repeats", type=int_range(1), default=5, help="timed calls, median reported (default 5)")
        add_common_flags(p, progress=False, quiet=False, why_not="it prints only its result")
        a = p.parse_args(argv[1:])
        from .common.threads import apply_threads

        apply_threads(a.threads)
        r = bench_keyframes(a.batch, a.frames, a.dims, a.reduction, a.repeats, a.device)
        print(f"VW keyframe selection on {r['shape']} (reduction {r['reduction']}, {r['device']}): "
              f"{r['median_s'] * 1000:.2f} ms (median of {len(r['times_s'])})")
        return 0
    if argv and argv[0] == "steps":
        argv = argv[1:]
    p = argparse.ArgumentParser(prog="smdm bench", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    main_bench(p.parse_args(argv), p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
