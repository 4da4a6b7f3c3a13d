"""``smdm bench``: what sparse keyframe mode saves, dense and sparse side by side in one run."""
from __future__ import annotations

import argparse
import os
import sys
from typing import Any, Dict, List, Optional, Tuple

import torch

from ..core.config import BACKENDS
from ..runtime.compile import COMPILE_MODES
from ..training.benchmark import MODES, TARGETS, bench_keyframes, run_bench
from ..training.workloads import FSQ_CHOICES, WORKLOADS, family_choices
from .common.args import (add_common_flags, add_overwrite, float_range, int_range, note_printer, output_path,
                          progress_of, resolve_device)
from .common.threads import apply_threads, load_average


# ----------------------------------------------------------------------------------------- printing
def _launch_cell(r: Dict[str, Any]) -> str:
    """A row's launches as the table shows them (— where none were counted)."""
    return "—" if r.get("launches") is None else str(r["launches"])


def row_line(r: Dict[str, Any]) -> str:
    """One result row as a progress line (stderr, as the cell is measured)."""
    ov = f" overhead {100 * r['overhead_share']:.1f}%" if "overhead_share" in r else ""
    return (f"{r['arch']} {r['mode']:6s} {r.get('compile_applied', 'eager'):15s} {r['variant']:10s} "
            f"{r['median_s'] * 1000:9.1f} ms {_launch_cell(r):>6s} launches "
            f"x{r['speedup']:.2f} (cpu x{r['cpu_speedup']:.2f}){ov}")


def _fsq_note(result: Dict[str, Any]) -> str:
    """Which side had FSQ keys, in words."""
    fam = result.get("family", "mdm")
    if fam in WORKLOADS and not WORKLOADS.get(fam).fsq:
        return "n/a (no softmax attention keys)"
    return FSQ_CHOICES[result.get("fsq", "paper")]


def _compile_label(mode: str) -> str:
    """``eager`` or ``torch.compile MODE``."""
    return "eager" if mode in ("none", "eager") else f"torch.compile {mode}"


def markdown(result: Dict[str, Any]) -> str:
    """The result of :func:`~smdm_plugin.training.benchmark.run_bench` as the printed table: the
    setting line, one row per cell, what the launches count, and the targets at 80% (not for ``--quick``)."""
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
    lines += ["", "launches: kernel launches of the timed call, counted as CUDA runs them (smdm_plugin.runtime.launches; "
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


# ----------------------------------------------------------------------------------------- CLI
QUICK = {"batch": 4, "frames": 60, "repeats": 1, "warmup": 0}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--family", default="mdm", choices=family_choices(),
                   help="model family to time, on its in-package model: mdm (TinyMDM at MDM's size), "
                        "motiondiffuse (MotionDiffuse's MotionTransformer layout); default mdm")
    p.add_argument("--root", default=None,
                   help="--family motiondiffuse: a MotionDiffuse checkout (the folder holding text2motion/) whose "
                        f"own MotionTransformer to time (default ${WORKLOADS.get('motiondiffuse').root_env} when set, else "
                        "the in-package one with the same layout)")
    p.add_argument("--arch", nargs="+", default=None, choices=list(WORKLOADS.get("mdm").archs),
                   help="MDM variants to time: trans_enc, trans_dec (the default: both), dip (DiP's prefix "
                        "completion, 20 + 40 frames), doubletake (priorMDM's model, its first take's handshake "
                        "frames forced at sampling); --family mdm only")
    p.add_argument("--reductions", nargs="+", type=float_range(0.0, 1.0, hi_open=True), default=[0.6, 0.7, 0.8, 0.9],
                   help="fractions of frames dropped, each in [0, 1)")
    p.add_argument("--batch", type=int_range(1, 65536), default=None, help="motions per batch (default 64)")
    p.add_argument("--frames", type=int_range(2, 4096), default=None,
                   help="frames per motion (default 196; not --arch dip: DiP's 20 + 40)")
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
    p.add_argument("--out", default=None, type=output_path("file"),
                   help="write the result as <out>.json and the table as <out>.md")
    add_overwrite(p)
    add_common_flags(p)  # --no-progress: no per-cell lines on stderr


def busy_note(threads: int) -> Optional[str]:
    """A warning when other processes already keep the CPU busy (timings with several threads per
    process then suffer badly from oversubscription: threads wait on preempted partners)."""
    load = load_average()
    cores = os.cpu_count() or 1
    if load is not None and threads > 1 and load > cores:
        return (f"note: load average {load:.1f} on {cores} cores — other jobs are running; "
                f"{threads} threads per process will be slowed by oversubscription, consider --threads 1")
    return None


def output_paths(out: str) -> Tuple[str, str]:
    """``(json, md)`` for ``--out`` (``x``, ``x.json`` or ``x.md`` all give ``x.json`` + ``x.md``)."""
    base, ext = os.path.splitext(out)
    base = base if ext.lower() in (".json", ".md") else out
    return base + ".json", base + ".md"


def check_family_options(args: argparse.Namespace, parser: argparse.ArgumentParser) -> Optional[str]:
    """Refuse the options ``--family`` has no use for (one argparse line), fill ``args.fsq``; returns
    the upstream checkout to take the model class from (``--root``, else the workload's environment
    variable; None: the in-package model)."""
    work = WORKLOADS.get(args.family)
    bad = [a for a in args.arch or () if a not in work.archs]
    if bad:
        parser.error(f"argument --arch: {bad[0]!r} is an MDM architecture; --family {args.family} has no "
                     "--arch choice (leave it out)")
    if args.fsq not in (None, "off") and not work.fsq:
        parser.error(f"argument --fsq: --family {args.family} has no softmax attention keys to quantise "
                     "(linear attention); leave --fsq out")
    args.fsq = args.fsq or ("paper" if work.fsq else "off")
    # settings that cannot apply: refused, never dropped
    if args.backend != "auto" and not work.fsq:        # (no softmax attention: no keyframe attention backend)
        parser.error(f"argument --backend: --family {args.family} has no keyframe attention backend to choose "
                     "(linear attention); leave --backend out")
    if args.backend != "auto" and any(m != "none" for m in args.compile_mode or ()):
        parser.error(f"argument --backend: a compiled model runs the compact backend (--compile "
                     f"{' '.join(args.compile_mode)}); leave --backend out, or time --compile none")
    if args.frames is not None and "dip" in (args.arch or ()):
        parser.error("argument --frames: --arch dip runs DiP's own 20 prefix + 40 predicted frames; leave --frames "
                     "out" + (" (or time dip apart)" if len(set(args.arch)) > 1 else ""))
    if args.fastpath and set(args.modes) == {"train"}:   # a setting that cannot apply: refused, never dropped
        parser.error("argument --fastpath: torch's fast path runs only without autograd (--modes sample, loop); "
                     "--modes train never takes it")
    root = args.root if args.root is not None else (os.environ.get(work.root_env) or None if work.root_env else None)
    if root is not None:
        try:
            work.check_root(root)
        except ValueError as e:
            parser.error(str(e).replace("--root:", "argument --root:", 1))
    return root


def fill_defaults(args: argparse.Namespace) -> None:
    """The sizes the user left out (``--quick``: :data:`QUICK`) and the compile modes of the device."""
    defaults = QUICK if args.quick else {"batch": 64, "frames": 196, "repeats": 3, "warmup": 1}
    for k, v in defaults.items():
        if getattr(args, k) is None:
            setattr(args, k, v)
    if args.compile_mode is None:
        args.compile_mode = ["none", "reduce-overhead"] if resolve_device(args.device).type == "cuda" else ["none"]


def checked_outputs(args: argparse.Namespace, parser: argparse.ArgumentParser) -> Optional[Tuple[str, str]]:
    """``--out``'s two files, refused (one argparse line) when one exists without ``--overwrite``."""
    from ..io.files import OutputExistsError, check_new_file

    if not args.out:
        return None
    if args.out.endswith(("/", os.sep)) or os.path.isdir(args.out):
        parser.error(f"argument --out: expected a file path (<out>.json and <out>.md are written), got the folder "
                     f"{args.out!r}")
    paths = output_paths(args.out)
    try:
        for p in paths:
            check_new_file(p, args.overwrite, "--out")
    except OutputExistsError as e:
        parser.error(str(e))
    return paths


def main_bench(args: argparse.Namespace, parser: argparse.ArgumentParser) -> Dict[str, Any]:
    """``smdm bench`` after parsing: check, run, print the table (and write ``--out``)."""
    from ..io.files import atomic_write_json, atomic_write_text

    root = check_family_options(args, parser)
    fill_defaults(args)
    paths = checked_outputs(args, parser)
    apply_threads(args.threads)
    note = busy_note(torch.get_num_threads()) if resolve_device(args.device).type == "cpu" else None
    say = note_printer(args)
    if note:
        say(note, file=sys.stderr)
    on_row = (lambda row: print(row_line(row), file=sys.stderr, flush=True)) if progress_of(args) else None
    result = run_bench(args.arch, args.reductions, args.batch, args.frames, args.repeats, args.warmup, args.device,
                       args.quick, args.backend, args.steps, args.fastpath, args.modes, args.amp, args.compile_mode,
                       on_row=on_row, fsq=args.fsq, family=args.family, root=root)
    table = markdown(result)
    print(table)
    if paths:
        atomic_write_json(paths[0], result)
        atomic_write_text(paths[1], table + "\n")
        say(f"\nwrote {paths[0]} and {paths[1]}")
    return result


def main_keyframes(argv: List[str]) -> int:
    """``smdm bench keyframes``: VW selection alone, one line."""
    p = argparse.ArgumentParser(prog="smdm bench keyframes", description="time VW keyframe selection")
    p.add_argument("--batch", type=int_range(1, 65536), default=64, help="motions per call (default 64)")
    p.add_argument("--frames", type=int_range(2, 4096), default=196, help="frames per motion (default 196)")
    p.add_argument("--dims", type=int_range(1, 4096), default=64,
                   help="selection features per frame (default 64: 21 joints x 3 + frame index)")
    p.add_argument("--reduction", type=float_range(0.0, 1.0, hi_open=True), default=0.8,
                   help="fraction of frames dropped, in [0, 1) (default 0.8)")
    p.add_argument("--repeats", type=int_range(1), default=5, help="timed calls, median reported (default 5)")
    add_common_flags(p, progress=False, quiet=False, why_not="it prints only its result")
    a = p.parse_args(argv)
    apply_threads(a.threads)
    r = bench_keyframes(a.batch, a.frames, a.dims, a.reduction, a.repeats, a.device)
    print(f"VW keyframe selection on {r['shape']} (reduction {r['reduction']}, {r['device']}): "
          f"{r['median_s'] * 1000:.2f} ms (median of {len(r['times_s'])})")
    return 0


def main(argv: Optional[List[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "keyframes":
        return main_keyframes(argv[1:])
    if argv and argv[0] == "steps":
        argv = argv[1:]
    p = argparse.ArgumentParser(prog="smdm bench", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    main_bench(p.parse_args(argv), p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
