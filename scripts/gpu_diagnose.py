#!/usr/bin/env python
"""Where a GPU check's cell goes wrong: the diagnostics behind docs/gpu.md's findings, on one CUDA GPU.

* ``errors``: CUDA against the CPU (as ``gpu_check.py`` checks) for the sampling call and loop of
  each MDM variant with parts of the recipe switched off (the Triton kernels, the dynamic update,
  FSQ keys, Lipschitz layers), and the dense model's own bf16 error (the floor a bf16 cell is
  judged against);
* ``syncs``: host synchronisations of one sparse training step and sampling call per model
  (``torch.cuda.set_sync_debug_mode``), each with the package's frames of its stack;
* ``profile``: the torch profiler's host-side table (self CPU time) of dense and sparse trans_enc
  bf16 training steps and sampling calls, and the counts of launches, copies and syncs;
* ``parts``: eager speed of trans_enc with parts of the recipe off, dense beside it (the GPU's
  version of ``scripts/host_time_parts.py``);
* ``kernels``: eager speed of trans_enc and trans_dec with each group of the package's Triton
  kernels switched the other way (on against the composite), dense beside it: which one each device
  should run (``TritonKernel(enabled=...)``; the CPU meter's answer: ``scripts/host_time.py --triton``);
* ``layout``: which head layouts each SDPA kernel takes in bf16 (copies into ``[B, S, H·e]``, views of
  a sequence-first projection, views of a batch-first one; MDM's and the folded FSQ heads, with and
  without a key mask; each case in a child process, so a kernel that breaks the CUDA context cannot
  stop the others), then the MDM models' bf16 calls with the package's layout copies on and off
  (``use_layout_copies``): speed beside dense, and each against the CPU;
* ``optimizer``: what a ``--sparse_compile`` upstream run does around its captured steps (0.9.7):
  the fused AdamW resumed from a foreach state as MDM resumes (against foreach, host syncs), a fused
  state in torch's AdamW, the logged norms read in one sync (against upstream's per-tensor reads),
  the schedule tables read on the device (against upstream's copy per call); 0.9.8: the sampling
  loop's timesteps and ``timestep_map`` made on the device, the timestep sampler's and the batches'
  pinned copies, the training log's losses read at the dump (each against upstream's, with its syncs).

    python scripts/gpu_diagnose.py --out DIR [--sections errors syncs profile parts kernels layout optimizer]
"""
from __future__ import annotations

import argparse
import collections
import importlib.util
import statistics
import subprocess
import sys
import time
import traceback
import warnings
from pathlib import Path
from typing import Callable, Dict, List, Tuple

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from smdm_plugin.core.attention import use_layout_copies  # noqa: E402
from smdm_plugin.core.checks import static_mode  # noqa: E402
from smdm_plugin.core.kernels import TRITON_KERNELS, use_triton_kernels  # noqa: E402
from smdm_plugin.training import benchmark, workloads  # noqa: E402
from smdm_plugin.training.timing import event_times  # noqa: E402

_spec = importlib.util.spec_from_file_location("gpu_check", Path(__file__).with_name("gpu_check.py"))
gcheck = importlib.util.module_from_spec(_spec)
sys.modules["gpu_check"] = gcheck
_spec.loader.exec_module(gcheck)

MDM = [m for m in gcheck.MODELS if m[0] == "mdm"]
#: the speed size (MDM's); ``--dry-run`` replaces it by the check's tiny size
BIG = gcheck.Sizes(False, 64, 196, 50)
PARTS = {"recipe": {}, "no FSQ": {"fsq": "off"}, "no Lipschitz": {"lipschitz": False},
         "neither": {"fsq": "off", "lipschitz": False}}


#: the package's Triton kernels in the groups one decision switches (forward with its backward; VW's
#: and the mask noise's own kernels together: since 0.10.2 a default call runs neither, a training
#: step runs the fused one, "VW with mask noise", which the plan's own kernel serves when it is off)
KERNEL_GROUPS = {"FSQ codes": ["FSQ code", "FSQ code gradient"],
                 "Lipschitz weights": ["Lipschitz weight", "Lipschitz weight gradient"],
                 "keyframe plan": ["keyframe plan"], "VW and mask noise": ["VW", "mask-noise"],
                 "VW with mask noise": ["VW with mask noise"]}
assert sorted(n for g in KERNEL_GROUPS.values() for n in g) == sorted(TRITON_KERNELS)


#: what ``gpu_check.run_values`` reads of its settings: the check's size and the compile backend
CHECK = gcheck.Settings(torch.device("cpu"), "inductor", gcheck.Sizes(True, 4, 40, 10), gcheck.Sizes(True, 4, 40, 10),
                        1, 0, 1, float("inf"), [], [], [], [])


def values(family: str, arch: str, call: str, device: torch.device, amp: str, reduction, **config) -> List[torch.Tensor]:
    """``gpu_check.run_values`` (eager) at the check's size, the dynamic update on at sampling
    (``dynamic_update=False`` in ``config``: off), with more sparse settings ``config``."""
    dynamic = config.pop("dynamic_update", call != "train")
    return gcheck.run_values(CHECK, family, arch, call, device, amp, "eager", reduction, dynamic=dynamic, **config)


def section_errors(dev: torch.device) -> None:
    print("## errors: largest |CUDA - CPU| / largest |CPU| (check size: tiny model, B=4, 40 frames, T=10)")
    print(f"tf32 matmul {torch.backends.cuda.matmul.allow_tf32}, cudnn tf32 {torch.backends.cudnn.allow_tf32}, "
          f"float32 matmul precision {torch.get_float32_matmul_precision()}")
    cases = [("recipe", {}, None), ("recipe, Triton kernels off", {}, False),
             ("dynamic update off", {"dynamic_update": False}, None), ("no FSQ", {"fsq": "off"}, None),
             ("no Lipschitz", {"lipschitz": False}, None), ("no FSQ, no dynamic update", {"fsq": "off",
                                                                                         "dynamic_update": False}, None)]
    for family, arch, name in gcheck.MODELS:
        for call in ("sample", "loop"):
            for label, config, triton_on in cases:
                if arch not in ("trans_enc", "trans_dec") and label != "recipe":
                    continue
                try:
                    with static_mode():
                        ref = values(family, arch, call, torch.device("cpu"), "fp32", gcheck.REDUCTION, **config)
                    use_triton_kernels(triton_on)
                    got = values(family, arch, call, dev, "fp32", gcheck.REDUCTION, **config)
                    got16 = values(family, arch, call, dev, "bf16", gcheck.REDUCTION, **config)
                    msg = f"fp32 {gcheck.relative_error(got, ref):.1e}, bf16 {gcheck.relative_error(got16, ref):.1e}"
                except Exception as e:  # noqa: BLE001
                    msg = "error: " + gcheck.one_line(e)
                finally:
                    use_triton_kernels(None)
                print(f"{name} {call} sparse [{label}]: {msg}", flush=True)
            with static_mode():
                ref = values(family, arch, call, torch.device("cpu"), "fp32", None)
            got = values(family, arch, call, dev, "fp32", None)
            got16 = values(family, arch, call, dev, "bf16", None)
            print(f"{name} {call} DENSE: fp32 {gcheck.relative_error(got, ref):.1e}, "
                  f"bf16 {gcheck.relative_error(got16, ref):.1e}", flush=True)


def section_syncs(dev: torch.device) -> None:
    print("## syncs: host synchronisations per call (sparse, bf16, MDM size B=64)")
    root = str(Path(__file__).resolve().parents[1] / "smdm_plugin")
    for family, arch, name in gcheck.MODELS:
        for call in ("train", "sample"):
            z = BIG
            work = workloads.WORKLOADS.get(family)
            data = work.batch(z.batch, z.frames, dev, z.quick, arch)
            model, diffusion = workloads.build(arch, gcheck.REDUCTION, dev, z.quick, z.steps, family=family,
                                               frames=z.frames, **({"dynamic_update": True} if call == "sample" else {}))
            fn = benchmark.step_fn(call, work, model, diffusion, data, dev, "bf16", "none", "inductor")
            fn()
            fn()
            if dev.type == "cuda":
                torch.cuda.synchronize()
            seen: Dict[str, int] = collections.Counter()
            old = warnings.showwarning

            def show(message, category, filename, lineno, file=None, line=None):  # noqa: ANN001
                frames = [f"{Path(f.filename).name}:{f.lineno} {f.name}" for f in traceback.extract_stack()
                          if f.filename.startswith(root)]
                seen[f"{str(message)[:60]} @ " + " < ".join(reversed(frames[-3:]))] += 1

            warnings.showwarning = show
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("always")
                    warnings.showwarning = show
                    if dev.type == "cuda":
                        torch.cuda.set_sync_debug_mode("warn")
                    try:
                        fn()
                    finally:
                        if dev.type == "cuda":
                            torch.cuda.set_sync_debug_mode(0)
            finally:
                warnings.showwarning = old
            print(f"{name} {call}: {sum(seen.values())} syncs", flush=True)
            for k, v in seen.most_common(8):
                print(f"    {v} x {k}")
            del model, fn
            gcheck.free(dev)


def section_profile(dev: torch.device, out: Path) -> None:
    print("## profile: trans_enc, bf16, MDM size B=64 (5 calls after 5 warm-ups)")
    z = BIG
    work = workloads.WORKLOADS.get("mdm")
    data = work.batch(z.batch, z.frames, dev, z.quick, "trans_enc")
    for call in ("train", "sample"):
        for reduction in (None, gcheck.REDUCTION):
            model, diffusion = workloads.build("trans_enc", reduction, dev, z.quick, z.steps, family="mdm",
                                               frames=z.frames,
                                               **({"dynamic_update": True} if call == "sample" and reduction else {}))
            fn = benchmark.step_fn(call, work, model, diffusion, data, dev, "bf16", "none", "inductor")
            for _ in range(5):
                fn()
            kind = "dense" if reduction is None else "sparse"
            avg, host, gpu, count = gcheck.profile_calls(fn, dev, 5)
            print(f"{call} {kind}: host self total {host:.1f} ms/call (profiled), GPU busy {gpu:.1f} ms/call; "
                  + ", ".join(f"{k} {v}" for k, v in sorted(count.items())), flush=True)
            table = avg.table(sort_by="self_cpu_time_total", row_limit=45, max_name_column_width=70)
            (out / f"profile_{call}_{kind}.txt").write_text(table)
            del model, fn, avg
            gcheck.free(dev)


def _syncs(dev: torch.device, fn: Callable[[], object]) -> object:
    """``(fn(), host synchronisations it made)``: CUDA's sync debug mode's warnings (None off CUDA)."""
    if dev.type != "cuda":
        return fn(), None
    torch.cuda.synchronize()
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            out = fn()
        finally:
            torch.cuda.set_sync_debug_mode(0)
    return out, sum("synchroniz" in str(w.message) for w in seen)


def section_optimizer(dev: torch.device) -> None:
    """What a ``--sparse_compile`` upstream run does around its captured steps on the device (0.9.7;
    checked on the CPU only): the fused AdamW across MDM's resume, the logged norms in one sync,
    the schedule tables read on the device."""
    import copy

    import numpy as np

    from smdm_plugin.families.mdm.upstream_optim import norms_in_one_sync
    from smdm_plugin.integrations.tables import extract_from_device_table
    from smdm_plugin.runtime.fused_optim import FusedAdamW

    print("## optimizer: upstream runs' optimizer step, norms and schedule tables on the device (0.9.7)")
    g = torch.Generator().manual_seed(0)
    w = 512 if dev.type == "cuda" else 32                   # MDM's width on the GPU; small on a CPU's dry run
    shapes = [(w, w), (w,), (2 * w, w), (263, w)] * 8

    def params() -> List[torch.Tensor]:
        return [torch.randn(s, generator=g).to(dev).requires_grad_() for s in shapes]

    def steps(opt: torch.optim.Optimizer, ps: List[torch.Tensor], n: int, seed: int) -> None:
        gg = torch.Generator().manual_seed(seed)
        for _ in range(n):
            for p in ps:
                p.grad = torch.randn(p.shape, generator=gg).to(dev)
            opt.step()

    kw = {"lr": 1e-4, "weight_decay": 0.0}
    a = params()
    first = torch.optim.AdamW(a, **kw)                       # upstream's (foreach) first run
    steps(first, a, 3, 1)
    saved = copy.deepcopy(first.state_dict())
    b, c = [p.detach().clone().requires_grad_() for p in a], [p.detach().clone().requires_grad_() for p in a]
    fused, plain = FusedAdamW(b, **kw), torch.optim.AdamW(c, **kw)
    fused.load_state_dict(copy.deepcopy(saved))
    plain.load_state_dict(copy.deepcopy(saved))
    fused.param_groups[0]["capturable"] = True               # MDM's _load_optimizer_state
    step_devices = {str(fused.state[p]["step"].device) for p in b}
    _, fused_syncs = _syncs(dev, lambda: steps(fused, b, 2, 2))
    _, plain_syncs = _syncs(dev, lambda: steps(plain, c, 2, 2))
    diff = max(float((x - y).abs().max()) for x, y in zip(b, c))
    print(f"AdamW resumed from a foreach state: fused {fused.param_groups[0]['fused']}, step on {sorted(step_devices)}, "
          f"max |fused - foreach| after 2 steps {diff:.2e}; syncs in 2 steps: fused {fused_syncs}, foreach {plain_syncs}",
          flush=True)
    d = [p.detach().clone().requires_grad_() for p in b]
    again = torch.optim.AdamW(d, **kw)
    again.load_state_dict(copy.deepcopy(fused.state_dict()))  # a fused state in torch's AdamW (no flag)
    steps(again, d, 1, 3)
    steps(fused, b, 1, 3)
    print(f"a fused state in torch's AdamW: fused {again.param_groups[0]['fused']}, "
          f"max |diff| after a step {max(float((x - y).abs().max()) for x, y in zip(b, d)):.2e}", flush=True)

    def read_each(trainer, grad_scale: float = 1.0):  # noqa: ANN001, ANN202 - upstream's sums: a read per norm
        def norm2(t: torch.Tensor) -> float:
            return torch.norm(t, p=2, dtype=torch.float32).item() ** 2
        params = trainer.master_params
        with torch.no_grad():
            p2, g2 = [norm2(p) for p in params], [norm2(p.grad) for p in params if p.grad is not None]
        return np.sqrt(sum(g2, 0.0)) / grad_scale, np.sqrt(sum(p2, 0.0))

    ps = params() + [torch.randn(s, generator=g).to(dev).half() for s in shapes[:8]]    # CLIP: float16
    for p in ps[:len(shapes)]:
        p.grad = torch.randn(p.shape, generator=g).to(dev)
    t = type("Trainer", (), {"master_params": ps})()
    want, want_syncs = _syncs(dev, lambda: read_each(t))
    got, got_syncs = _syncs(dev, lambda: norms_in_one_sync(read_each)(t))
    rel = max(abs(x - y) / max(abs(y), 1e-30) for x, y in zip(got, want))
    print(f"norms of {len(ps)} tensors: max relative difference {rel:.2e}; syncs upstream {want_syncs}, "
          f"one-sync {got_syncs}", flush=True)

    table = np.linspace(1e-4, 0.02, 50)
    tt = torch.randint(0, 50, (64,), generator=g).to(dev)

    def per_call(arr, timesteps, shape):  # noqa: ANN001 - upstream's _extract_into_tensor
        res = torch.from_numpy(arr).to(device=timesteps.device)[timesteps].float()
        while len(res.shape) < len(shape):
            res = res[..., None]
        return res.expand(shape)

    hooked = extract_from_device_table(per_call)
    hooked(table, tt, (64, 263, 1, 196))                    # the table made (one copy)
    shape = (64, 263, 1, 196)
    want, up_syncs = _syncs(dev, lambda: [per_call(table, tt, shape) for _ in range(6)])
    got, hook_syncs = _syncs(dev, lambda: [hooked(table, tt, shape) for _ in range(6)])
    same = all(torch.equal(x, y) for x, y in zip(got, want))
    print(f"6 schedule reads (a p_sample step): equal {same}; syncs upstream {up_syncs}, device table {hook_syncs}",
          flush=True)
    _loops(dev, g)


def _loops(dev: torch.device, g: torch.Generator) -> None:
    """0.9.8: upstream's loops around the captured steps (checked on the CPU only): 50 steps of
    timesteps (``th.tensor([i] * B, device)``) and of ``respace``'s ``timestep_map``; the timestep
    sampler's copies; five batches handed to the loop; 50 steps of losses logged (upstream:
    ``.item()`` and two ``.cpu()`` per loss) against
    :class:`~smdm_plugin.families.mdm.upstream_loop.Later` values read back at a dump."""
    import numpy as np

    from smdm_plugin.families.mdm import upstream_loop
    from smdm_plugin.integrations.timesteps import tensor as on_device

    timestep_map = list(range(0, 1000, 20))
    for name, make in (("torch", torch.tensor), ("hook", on_device)):
        out, syncs = _syncs(dev, lambda: [(make([i] * 64, device=dev), make(timestep_map, device=dev, dtype=torch.int64))
                                          for i in range(50)])
        if name == "torch":
            want, up = out, syncs
    same = all(torch.equal(x, y) and torch.equal(a, b) for (x, a), (y, b) in zip(out, want))
    print(f"50 steps of timesteps and timestep_map: equal {same}; syncs upstream {up}, hook {syncs}", flush=True)

    class Sampler:                                        # upstream's ScheduleSampler.sample, uniform
        def sample(self, batch_size, device):  # noqa: ANN001, ANN201
            p = np.ones(1000) / 1000
            idx = np.random.choice(len(p), size=(batch_size,), p=p)
            return (torch.from_numpy(idx).long().to(device),
                    torch.from_numpy(1 / (len(p) * p[idx])).float().to(device))

    np.random.seed(0)
    want, up = _syncs(dev, lambda: [Sampler().sample(64, dev) for _ in range(10)])
    np.random.seed(0)
    got, hook = _syncs(dev, lambda: [upstream_loop.sample_without_sync(Sampler.sample)(Sampler(), 64, dev)
                                     for _ in range(10)])
    same = all(torch.equal(a, b) for x, y in zip(want, got) for a, b in zip(x, y))
    print(f"10 timestep draws: equal {same}; syncs upstream {up}, pinned {hook}", flush=True)

    batch = [(torch.randn(64, 263, 1, 196, generator=g), {"y": {"lengths": torch.randint(40, 196, (64,), generator=g)}})
             for _ in range(5)]
    want, up = _syncs(dev, lambda: [(m.to(dev), c["y"]["lengths"].to(dev)) for m, c in batch])
    got, hook = _syncs(dev, lambda: [(m.to(dev), c["y"]["lengths"].to(dev))
                                     for m, c in upstream_loop.DeviceBatches(batch, dev)])
    same = all(torch.equal(a, b) for x, y in zip(want, got) for a, b in zip(x, y))
    print(f"5 batches to the loop: equal {same}; syncs upstream {up}, handed on the device {hook}", flush=True)

    losses = [torch.rand(64, generator=g).to(dev) for _ in range(50)]
    ts = torch.randint(0, 1000, (64,), generator=g).to(dev)
    want, up = _syncs(dev, lambda: [(v.mean().item(), ts.cpu().numpy(), v.cpu().numpy()) for v in losses])
    later, kept = _syncs(dev, lambda: [upstream_loop.Later((v.mean(), ts, v), lambda m, t, x: (m.item(), t.numpy(), x.numpy()))
                                       for v in losses])
    host, dump = _syncs(dev, lambda: upstream_loop._to_host([t for v in later for t in v.tensors]))
    got = [v.make(*(host[id(t)] for t in v.tensors)) for v in later]
    same = all(a[0] == b[0] and np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2]) for a, b in zip(want, got))
    print(f"50 steps of a logged loss: equal {same}; syncs upstream {up}, kept {kept}, at the dump {dump}", flush=True)
    _motiondiffuse_loop(dev, g)


def _motiondiffuse_loop(dev: torch.device, g: torch.Generator) -> None:
    """0.9.9: MotionDiffuse's step (``families/motiondiffuse/upstream_loop.py``; checked on the CPU
    only): the padding mask of device lengths against a row per sample, each length read from the
    device (as upstream's ``generate_src_mask`` reads them, before its write per padded frame), and 50 steps of the loss summed and printed as upstream's
    loop does (``logs[k] += loss.item()``, mean over ``log_every`` = 50)."""
    from smdm_plugin.families.motiondiffuse import upstream_loop as md

    def per_sample(T, length):  # noqa: ANN001, ANN202 -- a row per sample, each length read (as upstream's loop)
        return torch.stack([(torch.arange(T) < int(n)).float() for n in length])

    lengths = torch.randint(40, 197, (32,), generator=g).to(dev)
    want, up = _syncs(dev, lambda: per_sample(196, lengths).to(dev))
    got, hook = _syncs(dev, lambda: md.src_mask(196, lengths).to(dev))
    print(f"MotionDiffuse padding mask, B=32: equal {torch.equal(want, got)}; syncs upstream {up}, flag {hook}",
          flush=True)
    losses = [torch.rand((), generator=g).to(dev) for _ in range(50)]

    def summed(values):  # noqa: ANN001, ANN202 -- upstream's loop over 50 steps, then its print's read
        total = None
        for v in values:
            total = v if total is None else total + v
        return "%.17g" % (total / 50)

    want, up = _syncs(dev, lambda: summed([v.item() for v in losses]))
    got, hook = _syncs(dev, lambda: summed([md.LossValue.of(v) for v in losses]))
    print(f"MotionDiffuse, 50 steps of the loss printed: equal {want == got}; syncs upstream {up}, "
          f"LossValue {hook} (at the print)", flush=True)


def section_parts(dev: torch.device) -> None:
    print("## parts: eager trans_enc at MDM size, B=64, 196 frames: ms per call (CUDA events, median of 20)")
    z = BIG
    work = workloads.WORKLOADS.get("mdm")
    data = work.batch(z.batch, z.frames, dev, z.quick, "trans_enc")
    for amp in ("bf16", "fp32"):
        for call in ("train", "sample"):
            fns = {}
            model, diffusion = workloads.build("trans_enc", None, dev, z.quick, z.steps, family="mdm", frames=z.frames)
            fns["dense"] = benchmark.step_fn(call, work, model, diffusion, data, dev, amp, "none", "inductor")
            for label, config in PARTS.items():
                extra = dict(config, **({"dynamic_update": True} if call == "sample" else {}))
                model, diffusion = workloads.build("trans_enc", gcheck.REDUCTION, dev, z.quick, z.steps, family="mdm",
                                                   frames=z.frames, **extra)
                fns[label] = benchmark.step_fn(call, work, model, diffusion, data, dev, amp, "none", "inductor")
            print_medians(f"{amp} {call}", interleaved_medians({k: (fn, None) for k, fn in fns.items()}, dev,
                                                               lambda setting: None))
            del fns
            gcheck.free(dev)


def interleaved_medians(cases: Dict[str, Tuple[Callable[[], object], object]], dev: torch.device,
                        switch: Callable[[object], None]) -> Dict[str, float]:
    """ms per call of each case ``name: (fn, setting)``, ``switch(setting)`` before its calls and
    ``switch(None)`` (the defaults) after: 3 warm-up calls each, then 20 rounds over the cases in
    turn, CUDA events, medians."""
    def run(fn, setting, warm: int) -> List[float]:  # noqa: ANN001
        switch(setting)
        try:
            return event_times(fn, dev, 1, warm)
        finally:
            switch(None)

    times: Dict[str, List[float]] = {k: [] for k in cases}
    for fn, setting in cases.values():
        run(fn, setting, 3)
    for _ in range(20):
        for k, (fn, setting) in cases.items():
            times[k] += run(fn, setting, 0)
    return {k: statistics.median(v) * 1e3 for k, v in times.items()}


def print_medians(label: str, med: Dict[str, float]) -> None:
    """One line: each case's ms and its speed-up over ``med["dense"]``."""
    print(f"{label}: " + ", ".join(f"{k} {v:.2f} ms ({med['dense'] / v:.2f}x)" for k, v in med.items()), flush=True)


def section_kernels(dev: torch.device) -> None:
    print("## kernels: eager sparse speed with each group of Triton kernels switched the other way "
          "(MDM size, B=64, 196 frames; ms per call, CUDA events, median of 20; dense beside it)")
    print("defaults: " + ", ".join(f"{n} {'on' if k.default else 'off'}" for n, k in sorted(TRITON_KERNELS.items())))
    z = BIG
    work = workloads.WORKLOADS.get("mdm")
    for arch in ("trans_enc", "trans_dec"):
        data = work.batch(z.batch, z.frames, dev, z.quick, arch)
        for amp in ("bf16", "fp32"):
            for call in ("train", "sample"):
                model, diffusion = workloads.build(arch, None, dev, z.quick, z.steps, family="mdm", frames=z.frames)
                dense = benchmark.step_fn(call, work, model, diffusion, data, dev, amp, "none", "inductor")
                model, diffusion = workloads.build(arch, gcheck.REDUCTION, dev, z.quick, z.steps, family="mdm",
                                                   frames=z.frames)
                sparse = benchmark.step_fn(call, work, model, diffusion, data, dev, amp, "none", "inductor")
                cases = {"dense": (dense, None), "sparse, defaults": (sparse, None)}
                for group, names in KERNEL_GROUPS.items():
                    flip = not TRITON_KERNELS[names[0]].default
                    cases[f"{group} {'on' if flip else 'off'}"] = (sparse, (flip, names))
                print_medians(f"{arch} {amp} {call}", interleaved_medians(
                    cases, dev, lambda setting: use_triton_kernels(*(setting or (None,)))))
                del dense, sparse, cases
                gcheck.free(dev)


#: the layout probe's cases: (sequence length, layout, heads, key mask, backend) in the order they run
LAYOUTS = ("copies", "seq-first views", "batch-first views")
HEADS = {"MDM heads": (128, 128), "folded FSQ heads": (8, 128)}      # (query/key size, value size)
BACKENDS = ("default", "CUDNN_ATTENTION", "FLASH_ATTENTION", "EFFICIENT_ATTENTION", "MATH")
PROBES = [(S, layout, heads, mask, backend) for S in (40, 196) for layout in LAYOUTS for heads in HEADS
          for mask in (False, True) for backend in BACKENDS]


def probe_layout(dev: torch.device, start: int) -> int:
    """Run :data:`PROBES` from ``start``, one line each (bf16, B=64, 4 heads; forward and backward
    against float32 math on copies): 0 when all ran, 3 when a case broke the CUDA context (the
    parent goes on from the next)."""
    from torch.nn.attention import SDPBackend, sdpa_kernel
    import torch.nn.functional as F
    B, H = (64, 4) if dev.type == "cuda" else (2, 4)
    for i in range(start, len(PROBES)):
        S, layout, heads, masked, backend = PROBES[i]
        e, ev = HEADS[heads]
        S = S if dev.type == "cuda" else 8
        g = torch.Generator(device="cpu").manual_seed(i)
        width = 2 * H * e + H * ev
        proj = torch.randn(S, B, width, generator=g).to(dev, torch.bfloat16)
        bias = torch.zeros(B, 1, 1, S, device=dev, dtype=torch.bfloat16)
        bias[::2, ..., S - S // 4:] = float("-inf")
        grad = torch.randn(B, H, S, ev, generator=g).to(dev, torch.bfloat16)

        def split(t):  # noqa: ANN001, ANN202
            q, k, v = t.split([H * e, H * e, H * ev], dim=-1)
            if layout == "copies":
                return [x.transpose(0, 1).contiguous().unflatten(-1, (H, -1)).transpose(1, 2) for x in (q, k, v)]
            if layout == "seq-first views":
                return [x.unflatten(-1, (H, -1)).permute(1, 2, 0, 3) for x in (q, k, v)]
            return [x.unflatten(-1, (H, -1)).transpose(1, 2) for x in (q, k, v)]   # t is [B, S, W]

        def call(t):  # noqa: ANN001, ANN202
            q, k, v = split(t)
            return F.scaled_dot_product_attention(q, k, v, attn_mask=bias if masked else None, scale=e ** -0.5)

        def run() -> torch.Tensor:
            t = (proj if layout != "batch-first views" else proj.transpose(0, 1).contiguous()).requires_grad_(True)
            out = call(t)
            out.backward(grad)
            return torch.cat([out.float().flatten(), t.grad.float().flatten()])

        ref_t = proj.float().requires_grad_(True)
        with sdpa_kernel([SDPBackend.MATH]):
            q, k, v = [x.transpose(0, 1).unflatten(-1, (H, -1)).transpose(1, 2)
                       for x in ref_t.split([H * e, H * e, H * ev], dim=-1)]
            ref_out = F.scaled_dot_product_attention(q, k, v, attn_mask=bias.float() if masked else None,
                                                     scale=e ** -0.5)
            ref_out.backward(grad.float())
        ref_g = ref_t.grad if layout != "batch-first views" else ref_t.grad.transpose(0, 1)
        ref = torch.cat([ref_out.flatten(), ref_g.flatten()])
        name = f"S={S} {layout}, {heads}, {'key mask' if masked else 'no mask'}, {backend}"
        try:
            ctx = sdpa_kernel([getattr(SDPBackend, backend)]) if backend != "default" else _null()
            with ctx:
                got = run()
                if dev.type == "cuda":
                    torch.cuda.synchronize()
                err = ((got - ref).abs().max() / ref.abs().max()).item()
                ms = statistics.median(event_times(run, dev, 10, 3)) * 1e3
            print(f"[{i}] {name}: ok, error {err:.1e}, {ms:.3f} ms forward+backward", flush=True)
        except Exception as e:  # noqa: BLE001
            print(f"[{i}] {name}: {type(e).__name__}: {gcheck.one_line(e)[:160]}", flush=True)
            try:
                torch.ones(1, device=dev).add_(1).item()
            except Exception:  # noqa: BLE001 - the context is gone: the parent starts a new process
                print(f"[{i}] (CUDA context lost)", flush=True)
                return 3
    return 0


class _null:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *a) -> None:  # noqa: ANN002
        return None


def probe_models(dev: torch.device) -> None:
    """The MDM models' bf16 calls at MDM size with the layout copies on and off (default): ms per
    call beside dense (CUDA events, median of 20), then each against the CPU (check size)."""
    z = BIG
    work = workloads.WORKLOADS.get("mdm")
    for arch in ("trans_enc", "trans_dec"):
        data = work.batch(z.batch, z.frames, dev, z.quick, arch)
        for call in ("train", "sample"):
            model, diffusion = workloads.build(arch, None, dev, z.quick, z.steps, family="mdm", frames=z.frames)
            dense = benchmark.step_fn(call, work, model, diffusion, data, dev, "bf16", "none", "inductor")
            model, diffusion = workloads.build(arch, gcheck.REDUCTION, dev, z.quick, z.steps, family="mdm",
                                               frames=z.frames)
            sparse = benchmark.step_fn(call, work, model, diffusion, data, dev, "bf16", "none", "inductor")
            cases = {"dense": (dense, None), "sparse, copies": (sparse, True), "sparse, views": (sparse, None)}
            print_medians(f"{arch} bf16 {call}", interleaved_medians(cases, dev, use_layout_copies))
            del dense, sparse, cases
            gcheck.free(dev)
            with static_mode():
                ref = values("mdm", arch, call, torch.device("cpu"), "fp32", gcheck.REDUCTION)
            errs = []
            for switch in (True, None):
                use_layout_copies(switch)
                try:
                    errs.append(gcheck.relative_error(values("mdm", arch, call, dev, "bf16", gcheck.REDUCTION), ref))
                finally:
                    use_layout_copies(None)
            print(f"{arch} bf16 {call} against the CPU (check size): copies {errs[0]:.1e}, views {errs[1]:.1e}",
                  flush=True)


def section_layout(dev: torch.device, dry: bool) -> None:
    print("## layout: which bf16 head layouts each SDPA kernel takes (B=64, 4 heads; forward+backward against "
          "float32 math), then the models with the layout copies on and off")
    start = 0
    child = [sys.executable, __file__] + (["--dry-run"] if dry else []) + ["--child"]
    while start < len(PROBES):
        p = subprocess.run(child + ["probe", str(start)], stdout=subprocess.PIPE, text=True, timeout=600)
        print(p.stdout, end="", flush=True)
        done = [int(line[1:line.index("]")]) for line in p.stdout.splitlines() if line.startswith("[")]
        if p.returncode != 3:                     # 3: a case broke the CUDA context; else all ran (or a bug)
            break
        start = (max(done) if done else start) + 1
    p = subprocess.run(child + ["models", "0"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                       timeout=600)
    print(p.stdout, end="", flush=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default=".", help="folder for the profiler tables")
    p.add_argument("--sections", nargs="+", default=["errors", "syncs", "profile", "parts", "kernels"],
                   choices=["errors", "syncs", "profile", "parts", "kernels", "layout", "optimizer"])
    p.add_argument("--dry-run", action="store_true", help="on the CPU at the tiny size (checks that it runs)")
    p.add_argument("--child", nargs=2, metavar=("PART", "START"), help=argparse.SUPPRESS)
    a = p.parse_args()
    global BIG
    if a.dry_run:
        dev, BIG = torch.device("cpu"), gcheck.Sizes(True, 2, 24, 4)
    elif not torch.cuda.is_available():
        print("gpu_diagnose: no CUDA device here (--dry-run on a CPU)", file=sys.stderr)
        return 2
    else:
        dev = torch.device("cuda")
    warnings.simplefilter("ignore")
    if a.child:                                   # section_layout's child processes
        if a.child[0] == "probe":
            return probe_layout(dev, int(a.child[1]))
        probe_models(dev)
        return 0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    for s in a.sections:
        t0 = time.perf_counter()
        try:
            {"errors": lambda: section_errors(dev), "syncs": lambda: section_syncs(dev),
             "profile": lambda: section_profile(dev, out), "parts": lambda: section_parts(dev),
             "kernels": lambda: section_kernels(dev), "layout": lambda: section_layout(dev, a.dry_run),
             "optimizer": lambda: section_optimizer(dev)}[s]()
        except Exception:  # noqa: BLE001 - the other sections still run
            traceback.print_exc()
        print(f"({s}: {time.perf_counter() - t0:.0f} s)\n", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
