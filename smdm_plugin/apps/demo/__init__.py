"""``smdm demo``: sparse keyframes on real motion capture, with nothing to download."""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Dict, List, Optional, Tuple

import numpy as np
import torch

from ...io.files import atomic_open, atomic_write_json, atomic_write_text
from ..common.args import (add_common_flags, add_overwrite, float_range, int_range, note_printer, output_path,
                           progress_of, seed_type)
from ..common.keyframe_study import (FRAME_INDEX_SCALE, keyframe_markdown, keyframe_study, motion_source,
                                     plot_keyframes, require_windows, windows)

if TYPE_CHECKING:
    from ...runtime.distributed import DistContext
    from ...training.data import MotionSet
    from ...training.trainer import Trainer

NO_BVH = """smdm demo: no BVH motion capture found.
  Pass one or more files or folders:  smdm demo --bvh path/to/clips/
  or set SMDM_MOCAP to a folder of CMU .bvh files (cgspeed's BVH conversion of mocap.cs.cmu.edu),
  or give neither: smdm demo then uses the CMU clips embedded in the package."""

# ----------------------------------------------------------------------------------------- training
def motion_features(joints: np.ndarray) -> np.ndarray:
    """The demo's training representation ``[T, 66]`` (``joints66``, see
    :mod:`smdm_plugin.io.representation`) from joints ``[T, 22, 3]`` (metres): joints 1..21 minus
    the root (63), root height (1), root x, z (2) with the first frame's root moved to x = z = 0."""
    from ...io.representation import canonical_xz, joints_to_joints66

    return joints_to_joints66(canonical_xz(np.asarray(joints, np.float32))).astype(np.float32)


def training_crops(clips, length: int, stride: int) -> List[np.ndarray]:
    """All crops of ``length`` frames (every ``stride`` frames) as joints ``[length, 22, 3]``."""
    crops = [j[s:s + length] for _, j in clips for s in range(0, max(1, len(j) - length + 1), stride)
             if len(j[s:s + length]) == length]
    if not crops:
        raise ValueError(f"smdm demo: no clip has {length} frames; use --frames with a smaller value")
    return crops


def equal_step_rates(train: Dict[str, Any]) -> Dict[str, float]:
    """Steps per second of each trainer over the race's equal steps (what ``speed_ratio`` compares:
    sparse / dense of these is exactly it), from :func:`~smdm_plugin.training.trainer.race_fair`'s result."""
    eq = train["equal_steps"]
    return {name: eq["steps"] / max(sec, 1e-9) for name, sec in eq["seconds"].items()}


def plot_losses(train: Dict[str, Any], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    rates = equal_step_rates(train)   # the legend and the title give the same measure
    for name, col in (("dense", "tab:blue"), ("sparse", "tab:red")):
        r = train[name]
        if not r["loss"]:
            continue
        loss = np.asarray(r["loss"])
        k = max(1, len(loss) // 25)
        smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
        lab = f"{name} ({rates[name]:.2f} steps/s over the first {train['equal_steps']['steps']} steps)"
        axes[0].plot(np.arange(len(smooth)) + k, smooth, color=col, label=lab)
        axes[1].plot(np.asarray(r["time"])[k - 1:], smooth, color=col, label=lab)
    axes[0].set_xlabel("training step")
    axes[1].set_xlabel("training time (s)")
    for ax in axes:
        ax.set_ylabel("diffusion loss (x0 MSE, normalised)")
        ax.set_yscale("log")
        ax.legend()
    fig.suptitle(f"dense vs sparse ({int(round(train['spec']['reduction'] * 100))}% of frames dropped): "
                 f"sparse runs {train['speed_ratio']:.2f}x the steps per second")
    fig.tight_layout()
    try:  # atomic; a failed write (a full disk) names the file
        with atomic_open(path, "wb") as f:
            fig.savefig(f, format="png", dpi=110)
    finally:
        plt.close(fig)


def limits_note(args: argparse.Namespace, train: Dict[str, Any], crops: int) -> str:
    """What this run's model sizes and training time can and cannot show, and the commands for a real
    run (appended to training.md and inbetween.md)."""
    steps = ", ".join(f"{n} {train[n]['steps']}" for n in ("dense", "sparse") if n in train)
    seconds = sum(float(train[n].get("seconds", 0.0)) for n in ("dense", "sparse") if n in train)
    return (f"**What this demo can and cannot show.** The models are TinyMDM {args.latent}-D × {args.layers} "
            f"layer(s), trained for {seconds:.1f} s in total ({steps} steps) on {crops} crops of "
            f"{args.frames} frames{' (--quick)' if args.quick else ''}. MDM is 512-D × 8 layers, trained for days "
            "on HumanML3D's ~29,000 motions. So this run shows that dense and sparse train and sample through "
            "the same code on real motion capture, how well each keyframe selector rebuilds the motion, and the "
            "relative cost of a step at this size. It cannot show the quality of a trained model: after minutes "
            "of training the samples jitter, the in-betweens jump onto the keyframes instead of passing "
            "through them smoothly, and at this size fixed costs make dense and sparse "
            "sample in about the same time. For a real run: `smdm train --data DIR --sparse` on HumanML3D (or "
            "MDM itself with `--sparse`, docs/mdm.md), `smdm bench` for speed at MDM size, and `smdm inbetween "
            "--model DIR` on the trained folder.")


# ----------------------------------------------------------------------------------------- in-betweening
def inbetween_demo(bundles: Dict[str, Any], clip: Tuple[str, np.ndarray], length: int, every: int, out: str,
                   seed: int, device: Any, gif: bool, progress: bool, stride: int = 1, note: str = "") -> str:
    """In-between one window of ``clip`` (keyframes every ``every`` frames and the last) with each
    model of ``bundles``; writes ``inbetween.md`` and ``inbetween.gif`` to ``out``; returns the table."""
    from ...metrics.inbetween_metrics import keyframe_metrics
    from ..common.bundle_inbetween import plan_keyframes, run_inbetween, summary_markdown
    from ..common.motion_files import LoadedMotion

    name, joints = clip
    source = LoadedMotion(joints, "bvh", name, 20.0)
    kf = plan_keyframes(len(joints), None, every, 0, length, length)
    rows, results = [], {}
    for label, b in bundles.items():
        r = run_inbetween(b, source, kf, samples=1, seed=seed, device=device, progress=progress)
        results[label] = r
        given = np.zeros(length, bool)
        given[kf.frames] = True
        rows.append({"model": label, "feature_error": r.feature_error, "seconds": r.seconds,
                     **keyframe_metrics(r.joints, r.target, given, 20.0, reference=True)})
    table = (f"In-betweening {name} frames 0-{length - 1}{note}: {len(kf.frames)} keyframes (every {every} "
             f"frames and the last) imposed by imputation; the sparse model also keeps them as keyframe tokens.\n\n"
             + summary_markdown(rows))
    atomic_write_text(os.path.join(out, "inbetween.md"), table + "\n")
    if gif:
        from ..common.animation import Panel, render_gif

        panels = [Panel(joints[:length], "motion capture", kf.frames)]
        panels += [Panel(r.joints[0], f"{label} model", kf.frames) for label, r in results.items()]
        render_gif(panels, os.path.join(out, "inbetween.gif"), fps=20.0, stride=stride, overwrite=True,
                   progress=progress, suptitle=f"{name}: in-betweening {len(kf.frames)} keyframes (red)")
    return table


# ----------------------------------------------------------------------------------------- CLI
#: options ``--quick`` shrinks, unless given: (normal default, quick value)
#: (--frames stays 120 in --quick: the README's next commands place keyframes up to frame 119 on its models)
QUICK = {"max_clips": (None, 1), "reductions": ([0.6, 0.7, 0.8, 0.9], [0.8]),
         "batch": (32, 4), "latent": (256, 32), "layers": (4, 1)}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--bvh", nargs="+", default=None, help="BVH files or folders (default: see above)")
    p.add_argument("--out", default=os.path.join("smdm_out", "demo"), type=output_path(), help="output folder")
    add_overwrite(p)
    p.add_argument("--minutes", type=float_range(0, 24 * 60, lo_open=True), default=None,
                   help="training time in minutes, dense + sparse together (default 2; with --quick, 3 steps each "
                        "unless --minutes is given)")
    p.add_argument("--reductions", nargs="+", type=float_range(0, 1, hi_open=True), default=None,
                   help="keyframe study: fractions of frames dropped (default 0.6 0.7 0.8 0.9)")
    p.add_argument("--train-reduction", type=float_range(0, 1, hi_open=True), default=0.8,
                   help="fraction of frames the sparse model drops in training, in [0, 1) (default 0.8)")
    p.add_argument("--frames", type=int_range(20, 196), default=120,
                   help="training crop and in-betweening length (frames at 20 fps; default 120)")
    p.add_argument("--batch", type=int_range(1, 4096), default=None, help="default 32")
    p.add_argument("--latent", type=int_range(4, 4096), default=None, help="a multiple of 4 (heads); default 256")
    p.add_argument("--layers", type=int_range(1, 64), default=None, help="default 4")
    p.add_argument("--every", type=int_range(2, 196), default=30, help="in-betweening: a keyframe every EVERY frames (default 30)")
    p.add_argument("--seed", type=seed_type, default=0, help="random seed (default 0)")
    p.add_argument("--max-clips", type=int_range(1), default=None, help="use at most this many clips (default: all)")
    p.add_argument("--frame-index-scale", type=float_range(0, 100), default=FRAME_INDEX_SCALE, metavar="M",
                   help="metres per frame appended to the joint positions for VW selection, in the keyframe "
                        f"table and in the sparse model's training (default {FRAME_INDEX_SCALE}, the library's)")
    p.add_argument("--no-gif", action="store_true", help="skip the in-betweening animation")
    p.add_argument("--evaluator", default=None, metavar="EDIR",
                   help="motion evaluator folder for FID and diversity: one that reads joints66 features (66-D), e.g. "
                        "from 'smdm evaluator train' or a previous demo's OUT/evaluator (default: train a small one "
                        "on the demo's training clips at start, about 15-30 s, and save it to OUT/evaluator)")
    p.add_argument("--no-evaluator", action="store_true", help="no FID / diversity: skip the evaluator (default: off)")
    p.add_argument("--quick", action="store_true",
                   help="a smoke run: 1 clip, a tiny model, 3 steps, no progress bars (options you give "
                        "are kept)")
    add_common_flags(p)


def apply_quick(args: argparse.Namespace) -> List[str]:
    """Fill the options of :data:`QUICK` the user did not give (None) with the quick or normal
    value; returns the ``--quick`` settings that were applied, for the log."""
    applied = []
    for name, (normal, quick) in QUICK.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else normal)
            if args.quick:
                applied.append(f"--{name.replace('_', '-')} {' '.join(map(str, quick)) if isinstance(quick, list) else quick}")
    return applied


class DemoError(Exception):
    """A reason the demo cannot go on: printed as is to stderr, exit status 2."""


@dataclass
class DemoRun:
    """One run of the demo: its checked options (``args``), this process's place under torchrun
    (``ctx``), how it prints (``say``: rank 0's notes, nothing elsewhere) and whether it shows
    progress bars."""

    args: argparse.Namespace
    ctx: "DistContext"
    say: Callable[..., None]
    progress: bool

    @property
    def main_rank(self) -> bool:
        return bool(self.ctx.is_main)

    @property
    def device(self) -> torch.device:
        return self.ctx.device

    def path(self, name: str) -> str:
        """``name`` in the output folder."""
        return os.path.join(self.args.out, name)


@dataclass
class DemoMotion:
    """The motion the demo runs on: where it came from (``source``, the BVH ``files``, the ``skipped``
    ones with their reasons) and the ``clips`` (name, joints ``[T, 22, 3]``); with three clips or
    more the last is ``held`` out of training (None: every clip trains)."""

    source: str
    files: List[str]
    skipped: List[Tuple[str, str]]
    clips: List[Tuple[str, np.ndarray]]
    held: Optional[Tuple[str, np.ndarray]] = None

    @property
    def train_clips(self) -> List[Tuple[str, np.ndarray]]:
        return [c for c in self.clips if c is not self.held]


@dataclass
class EvaluatorChoice:
    """The motion evaluator behind FID / diversity (None: none), what it reports about itself
    (``info``) and how the report names it (``source``)."""

    evaluator: Optional[Any] = None
    info: Dict[str, Any] = field(default_factory=dict)
    source: Optional[str] = None


@dataclass
class DemoTraining:
    """Dense and sparse trained in the race: the ``trainers``, the race's record ``train`` (what
    summary.json keeps), the equal-steps weights (``equal_step_states``), the training data and its
    normalisation, and the diffusion steps."""

    trainers: Dict[str, "Trainer"]
    train: Dict[str, Any]
    equal_step_states: Dict[str, Dict[str, torch.Tensor]]
    data: "MotionSet"
    mean: np.ndarray
    std: np.ndarray
    diffusion_steps: int


def load_motion(run: DemoRun) -> DemoMotion:
    """The clips (``--bvh``, ``$SMDM_MOCAP`` or the embedded ones), reported; the held-out clip."""
    args, say = run.args, run.say
    skipped: List[Tuple[str, str]] = []
    try:
        source, files, clips = motion_source(args.bvh, args.max_clips, log=say, skipped=skipped,
                                             min_frames=args.frames)
    except ValueError as e:
        raise DemoError(f"smdm demo: {e}\n" + NO_BVH) from None
    say(f"smdm demo: motion from {source}" + (f": {len(files)} BVH file(s)" if files else ""))
    if skipped:
        say(f"  skipped {len(skipped)} of {len(files)} file(s) (reasons above)")
    if not clips:
        raise DemoError("smdm demo: none of the BVH files is a CMU skeleton this demo can map to 22 joints.\n"
                        + NO_BVH)
    say(f"  {len(clips)} clip(s): " + ", ".join(f"{n} ({len(j)} frames)" for n, j in clips))
    held = clips[-1] if len(clips) >= 3 and len(clips[-1][1]) >= args.frames else None
    return DemoMotion(source, files, skipped, clips, held)


def run_keyframe_study(run: DemoRun, motion: DemoMotion) -> Dict[str, Any]:
    """Step 1: every selector at every reduction on windows of the clips; rank 0 writes
    ``keyframes.md`` / ``.csv`` / ``.png`` and returns the study (``{}`` on the other ranks)."""
    args = run.args
    wins = windows(motion.clips, 196, max_windows=2 if args.quick else None)
    try:
        require_windows(wins, motion.clips)
    except ValueError as e:
        raise DemoError(f"smdm demo: error: {e}") from None
    if not run.main_rank:
        return {}
    study = keyframe_study(wins, args.reductions, seed=args.seed, frame_index_scale=args.frame_index_scale)
    table = keyframe_markdown(study)
    print("\n## Keyframes vs. reconstruction error\n\n" + table)
    atomic_write_text(run.path("keyframes.md"), table + "\n")
    atomic_write_text(run.path("keyframes.csv"), "method," + ",".join(
        str(r) for r in study["reductions"]) + "\n" + "".join(m + "," + ",".join(
            f"{study['mpjpe_mm'][m][r]:.3f}" for r in study["reductions"]) + "\n" for m in study["methods"]))
    name, start, win = wins[0]
    red_plot = 0.8 if 0.8 in args.reductions else args.reductions[0]
    plot_keyframes(win, f"{name} frames {start}-{start + len(win) - 1}", red_plot, run.path("keyframes.png"),
                   frame_index_scale=args.frame_index_scale)
    return study


def prepare_evaluator(run: DemoRun, train_clips: List[Tuple[str, np.ndarray]]) -> EvaluatorChoice:
    """The evaluator for FID (rank 0): ``--evaluator``, else one trained now on the training clips
    and saved as ``OUT/evaluator``; none with ``--no-evaluator``."""
    args, say = run.args, run.say
    if not run.main_rank or args.no_evaluator:
        return EvaluatorChoice()
    from .evaluator import load_demo_evaluator, train_demo_evaluator

    if args.evaluator:
        from ...metrics.evaluator.model import evaluator_info

        choice = EvaluatorChoice(load_demo_evaluator(args.evaluator, run.device), evaluator_info(args.evaluator),
                                 f"the evaluator {args.evaluator}")
        say(f"\nevaluator: {args.evaluator}")
        return choice
    say(f"\n## Evaluator (FID): training a small one on the {len(train_clips)} training clip(s)")
    try:
        evaluator, info = train_demo_evaluator(train_clips, run.path("evaluator"), args.seed, quick=args.quick,
                                               device=run.device, progress=run.progress)
    except ValueError as e:
        raise DemoError(str(e)) from None
    held_acc = info["metrics"].get("val")
    say(f"evaluator: {info['epochs']} epochs, {info['n_train']} windows, {info['seconds']:.1f} s"
        + (f"; held-out caption retrieval top-1 {held_acc['top1']:.2f} among {held_acc['pool_size']} "
           f"captions (chance {held_acc['chance_top1']:.2f}, {held_acc['n_motions']} windows)" if held_acc
           else "; no held-out windows"))
    return EvaluatorChoice(evaluator, info, f"the demo's own evaluator (OUT/evaluator: {info['epochs']} epochs on "
                           f"{info['n_train']} windows of {info['window']} frames, {info['captions']} captions)")


def train_dense_and_sparse(run: DemoRun, motion: DemoMotion, crops: List[np.ndarray]) -> DemoTraining:
    """Step 2: dense and sparse TinyMDM from the same weights on the same crops, raced to equal
    steps and equal time (:func:`~smdm_plugin.training.trainer.race_fair`)."""
    from ...core.config import SparseConfig
    from ...training.data import MotionSet, feature_stats
    from ...training.trainer import TrainConfig, Trainer, race_fair

    args, ctx = run.args, run.ctx
    feats = [motion_features(c) for c in crops]
    mean, std = feature_stats(feats)
    data = MotionSet.from_motions(feats, mean, std, max_frames=args.frames)
    model = {"latent_dim": args.latent, "ff_size": 2 * args.latent, "num_layers": args.layers, "num_heads": 4,
             "dropout": 0.1}
    diffusion_steps = 20 if args.quick else 50   # the paper's T (App. B.1)
    sparse = SparseConfig(reduction=args.train_reduction, feature="raw", frame_index_scale=args.frame_index_scale)
    trainers = {n: Trainer(TrainConfig(steps=0, batch=args.batch, lr=2e-4, diffusion_steps=diffusion_steps,
                                       seed=args.seed, model=model, sparse=sc), data, dist=ctx)
                for n, sc in (("dense", None), ("sparse", sparse))}
    seconds = 60.0 * (2.0 if args.minutes is None else args.minutes)
    steps_cap = 3 if args.quick and args.minutes is None else None   # --quick's 3 steps; a given --minutes is kept
    budget = f"{steps_cap} steps each (--quick)" if steps_cap else f"{seconds:.0f} s in total"
    run.say(f"\n## Training dense vs. sparse ({int(round(args.train_reduction * 100))}% dropped) for "
            f"{budget} on {run.device}: {len(data)} crops of {args.frames} frames from "
            f"{len(motion.train_clips)} clip(s), 66-D joint features, batch {_procs(ctx)}{args.batch}")
    train = race_fair(trainers, seconds, max_steps=steps_cap, progress=run.progress,
                      desc="training dense + sparse")
    snapshots = train.pop("equal_steps")
    train["equal_steps"] = {k: v for k, v in snapshots.items() if k != "states"}
    train.update(spec={"reduction": args.train_reduction, **model, "diffusion_steps": diffusion_steps},
                 batch=args.batch, world_size=ctx.world_size, global_batch=trainers["dense"].global_batch,
                 seed=args.seed)
    return DemoTraining(trainers, train, snapshots["states"], data, mean, std, diffusion_steps)


def _procs(ctx: "DistContext") -> str:
    """``"N processes x "`` under torchrun, else nothing (the batch's prefix)."""
    return f"{ctx.world_size} processes x " if ctx.world_size > 1 else ""


def score_models(run: DemoRun, motion: DemoMotion, trained: DemoTraining, bundles: Dict[str, Any],
                 ev: EvaluatorChoice, crops: List[np.ndarray]) -> Tuple[Dict[str, Dict[str, float]], str]:
    """:data:`SCORED_SAMPLES` samples of each model scored against the real motion (the held-out
    clip, else the training clips), FID and diversity when there is an evaluator (recorded in
    ``trained.train["evaluator"]``): ``(quality, the evaluator's note)``."""
    args = run.args
    reference = np.stack(training_crops([motion.held] if motion.held else motion.train_clips, args.frames,
                                        stride=args.frames))
    generated = generate_samples(bundles, args.frames, SCORED_SAMPLES, args.seed, run.device)
    quality = generation_quality(generated, reference)
    if ev.evaluator is None:
        return quality, ""
    if len(crops) < 2:
        run.say("no FID: fewer than 2 real training crops to compare with")
        return quality, ""
    from .evaluator import evaluator_note

    pool = np.stack(crops)   # the real crops the models trained on: FID's reference
    real = {"motion capture": real_set(reference)} if len(reference) >= 2 else {}
    floor_set = {}
    if len(pool) > SCORED_SAMPLES:  # FID of as many real crops as samples: the floor at this size
        pick = np.sort(np.random.default_rng(args.seed).choice(len(pool), SCORED_SAMPLES, replace=False))
        floor_set = {"floor": real_set(pool[pick])}
    scores = evaluator_scores({**generated, **real, **floor_set}, pool, ev.evaluator)
    floor = scores.pop("floor")["fid"] if floor_set else None
    for k, v in scores.items():
        quality[k].update(v)
    pool_clips = [n for n, j in motion.train_clips if len(j) >= args.frames]   # the clips training_crops used
    trained.train["evaluator"] = {"source": args.evaluator or "OUT/evaluator", "fid_pool": len(pool),
                                  "fid_floor": floor, "info": {k: v for k, v in ev.info.items() if k != "history"}}
    return quality, evaluator_note(ev.info, ev.source, len(pool), pool_clips, SCORED_SAMPLES, floor)


def training_report(run: DemoRun, motion: DemoMotion, trained: DemoTraining,
                    quality: Dict[str, Dict[str, float]], ev_note: str, limits: str) -> str:
    """The training table with the speed ratio, the scoring and the limits; printed and written to
    ``training.md``."""
    args, train = run.args, trained.train
    table = training_markdown(train, quality, ("held-out clip" if motion.held else "training clips"))
    table += (f"\n\nsparse / dense training speed: **{train['speed_ratio']:.2f}×** (TinyMDM latent "
              f"{args.latent}, {args.layers} layers, batch {_procs(run.ctx)}{args.batch}, {args.frames} frames). "
              f"Quality: {SCORED_SAMPLES} unconditional samples per model ({trained.diffusion_steps} diffusion "
              f"steps, sparse sampling: {sparse_sampling(trained.trainers['sparse'].model)}); j/s = jitter / speed "
              f"(1/s²), the jerk relative to how fast the motion moves.")
    if ev_note:
        table += "\n\n" + ev_note
    table += "\n\n" + limits
    print(table)
    atomic_write_text(run.path("training.md"), table + "\n")
    return table


def inbetween_step(run: DemoRun, motion: DemoMotion, bundles: Dict[str, Any], limits: str) -> None:
    """Step 3: both models in-between a window of the held-out clip (else the first clip);
    ``inbetween.md`` (with the limits) and ``inbetween.gif``."""
    args = run.args
    clip = motion.held or motion.clips[0]
    note = " (held out from training)" if motion.held else " (a training clip: too few clips to hold one out)"
    print(f"\n## In-betweening {clip[0]}{note}")
    table = inbetween_demo({k: bundles[k] for k in ("dense", "sparse")}, clip, args.frames, args.every, args.out,
                           args.seed, run.device, gif=not args.no_gif, progress=run.progress,
                           stride=2 if args.quick else 1, note=note)
    table += "\n\n" + limits
    atomic_write_text(run.path("inbetween.md"), table + "\n")
    print(table)


def write_summary(run: DemoRun, motion: DemoMotion, study: Dict[str, Any], train: Dict[str, Any],
                  seconds: float) -> None:
    """``summary.json``: the motion used, the keyframe study, the training record, the options."""
    args = run.args
    summary = {"source": motion.source, "files": motion.files, "skipped": [list(x) for x in motion.skipped],
               "clips": [[n, len(j)] for n, j in motion.clips], "keyframes": study, "training": train,
               "seconds": seconds, "options": {**{k: v for k, v in vars(args).items() if k != "folder"},
                                               "out": getattr(args, "folder", args.out)}}
    summary["keyframes"]["mpjpe_mm"] = {m: {str(r): v for r, v in d.items()} for m, d in study["mpjpe_mm"].items()}
    atomic_write_json(run.path("summary.json"), summary, indent=1)


def main_demo(args: argparse.Namespace) -> int:
    """Run the demo (options checked by :func:`main`); returns the exit status. Under torchrun every
    rank reads the motion and trains; rank 0 alone writes files and prints the tables."""
    from ...runtime.distributed import init_distributed, shutdown_distributed
    from ..common.threads import apply_threads

    t_start = time.perf_counter()
    apply_threads(args.threads)
    try:
        ctx = init_distributed(args.device)
    except ValueError as e:
        print(f"smdm demo: {e}", file=sys.stderr)
        return 2
    run = DemoRun(args, ctx, note_printer(args) if ctx.is_main else (lambda *a, **k: None),
                  not args.quick and progress_of(args))
    try:
        return _demo_steps(run, t_start)
    except DemoError as e:
        print(e, file=sys.stderr)
        return 2
    finally:
        shutdown_distributed(ctx)


def _demo_steps(run: DemoRun, t_start: float) -> int:
    """The demo's steps in order (see the module's docstring)."""
    args = run.args
    quick = apply_quick(args)
    if quick:
        run.say("smdm demo --quick: " + ", ".join(quick) + (", 3 training steps each" if args.minutes is None else "")
                + ", 20 diffusion steps")
    motion = load_motion(run)
    if run.main_rank:
        os.makedirs(args.out, exist_ok=True)
    study = run_keyframe_study(run, motion)
    try:
        crops = training_crops(motion.train_clips, args.frames, stride=max(1, args.frames // 8))
    except ValueError as e:
        raise DemoError(str(e)) from None
    ev = prepare_evaluator(run, motion.train_clips)
    trained = train_dense_and_sparse(run, motion, crops)
    if not run.main_rank:
        return 0
    plot_losses(trained.train, run.path("loss.png"))
    bundles = save_models(trained.trainers, args.out, args.frames, trained.mean, trained.std, trained.train,
                          [c[0] for c in motion.train_clips], run.device, trained.equal_step_states)
    quality, ev_note = score_models(run, motion, trained, bundles, ev, crops)
    trained.train["quality"] = quality
    limits = limits_note(args, trained.train, len(trained.data))
    training_report(run, motion, trained, quality, ev_note, limits)
    inbetween_step(run, motion, bundles, limits)
    write_summary(run, motion, study, trained.train, time.perf_counter() - t_start)
    run.say(f"\noutputs: {os.path.abspath(getattr(args, 'folder', args.out))}")
    return 0


#: unconditional samples scored per model (jitter, speed, foot skating; FID once an evaluator is given)
SCORED_SAMPLES = 32


@dataclass
class GeneratedSet:
    """Samples of one model, in every form a scorer needs: ``features [B, N, D]`` (the model's
    representation, de-normalised; ``representation`` names it), ``lengths [B]`` (valid frames) and
    ``joints [B, N, 22, 3]`` (metres, 20 fps)."""

    features: torch.Tensor
    lengths: torch.Tensor
    joints: torch.Tensor
    representation: str


def generate_samples(bundles: Dict[str, Any], frames: int, samples: int, seed: int, device: torch.device
                     ) -> Dict[str, GeneratedSet]:
    """``samples`` unconditional motions of ``frames`` frames from each model of ``bundles``, with the
    same noise for every model."""
    out: Dict[str, GeneratedSet] = {}
    for name, b in bundles.items():
        y = {"mask": torch.ones(samples, 1, 1, frames, dtype=torch.bool, device=device),
             "lengths": torch.full((samples,), frames, dtype=torch.long, device=device)}
        gen = torch.Generator(device=device).manual_seed(seed + 11)
        x = b.diffusion.p_sample_loop(b.model, (samples, len(b.mean), 1, frames), {"y": y}, device=device,
                                      generator=gen)
        feats = b.denormalise(x.squeeze(2).permute(0, 2, 1).float().cpu())
        out[name] = GeneratedSet(torch.as_tensor(feats), y["lengths"].cpu(),
                                 torch.as_tensor(b.representation.to_joints(feats)), b.representation.name)
    return out


def motion_scores(joints: torch.Tensor) -> Dict[str, float]:
    """Jitter (m/s³), mean joint speed (m/s), jitter per unit speed ``jps`` (1/s², the ratio of the
    set's means) and foot skating ratio of joints ``[B, N, 22, 3]`` (metres, 20 fps)."""
    from ...metrics import foot_skating_ratio, jitter, mean_speed

    j = torch.as_tensor(joints)
    jit, speed = float(jitter(j, fps=20)), float(mean_speed(j, fps=20))
    return {"jitter": jit, "speed": speed, "jps": jit / speed if speed > 0 else float("nan"),
            "foot_skating": float(foot_skating_ratio(j, fps=20))}


def generation_quality(generated: Dict[str, GeneratedSet], reference: np.ndarray) -> Dict[str, Dict[str, float]]:
    """:func:`motion_scores` of every model's samples and of the real motion ``reference`` joints
    ``[W, N, 22, 3]`` (metres) under ``'motion capture'``."""
    out = {name: motion_scores(g.joints) for name, g in generated.items()}
    out["motion capture"] = motion_scores(torch.from_numpy(np.asarray(reference, np.float32)))
    return out


def real_set(joints: np.ndarray) -> GeneratedSet:
    """Real motion ``joints [W, N, 22, 3]`` (metres, 20 fps) as a :class:`GeneratedSet` of the demo's
    representation (``joints66``, :func:`motion_features` per window), to score it as a model's samples."""
    j = np.asarray(joints, np.float32)
    feats = torch.from_numpy(np.stack([motion_features(w) for w in j]))
    return GeneratedSet(feats, torch.full((len(j),), j.shape[1], dtype=torch.long), torch.from_numpy(j), "joints66")


def evaluator_scores(generated: Dict[str, GeneratedSet], reference: np.ndarray,
                     evaluator: Optional[Any] = None) -> Dict[str, Dict[str, float]]:
    """The field's distribution metrics of each set of samples against real motion, in the
    co-embedding of ``evaluator`` (an :class:`~smdm_plugin.metrics.evaluator.model.Evaluator` reading
    ``generated[name].representation``; ``None``: ``{}``): ``{name: {'fid': ..., 'diversity': ...}}``
    — FID of ``generated[name].features [B, N, D]`` (valid frames ``.lengths [B]``) against the real
    joints ``reference [W, N, 22, 3]`` (metres; as ``joints66`` features), diversity of the samples
    (:func:`~smdm_plugin.metrics.diversity`, 300 or B − 1 random pairs). The demo's models are
    unconditional: no R-precision. ValueError (one line) when a set is not in the evaluator's
    representation."""
    if evaluator is None:
        return {}
    from ...metrics.evaluator.score import embed_motions
    from ...metrics.t2m import diversity, frechet_distance

    rep = evaluator.config.representation
    for name, g in generated.items():
        if g.representation != rep or g.features.shape[-1] != evaluator.config.dim_pose:
            raise ValueError(f"evaluator_scores: {name!r} is {g.representation} [.., {g.features.shape[-1]}], the "
                             f"evaluator reads {rep} [.., {evaluator.config.dim_pose}]")
    real = embed_motions(evaluator, real_set(reference).features)
    out: Dict[str, Dict[str, float]] = {}
    for name, g in generated.items():
        emb = embed_motions(evaluator, g.features, g.lengths)
        out[name] = {"fid": float(frechet_distance(real, emb)), "diversity": float(diversity(emb, seed=0)[0])}
    return out


def sparse_sampling(model: Any) -> str:
    """The sparse sampling settings of ``model`` in words (interpolation, dynamic update)."""
    from ...adapters.state import sparse_config_of

    c = sparse_config_of(model)
    if c is None:
        return "dense"
    steps = "" if c.sample_interpolation_steps is None else f" in the last {c.sample_interpolation_steps} steps"
    fill, D = c.sample_interpolation, int(getattr(model, "njoints", 0)) * int(getattr(model, "nfeats", 1))
    if fill == "auto" and D:                     # what auto resolves to for the model's features
        fill = f"{c.sample_fill(D)} fill (auto)"
    else:
        fill += " fill"
    return f"{fill}{steps}, dynamic VW update {'on' if c.dynamic else 'off'}"


def training_markdown(train: Dict[str, Any], quality: Dict[str, Dict[str, float]], reference: str) -> str:
    """The training table: per model steps, time, final loss, and the jitter per unit speed (j/s),
    jitter, speed and foot skating of its samples (plus FID etc. when an evaluator gave them). A
    model that trained on after the equal-steps point has two rows: at that step count
    (``<name>_equal_steps`` in ``quality``: "equal steps") and at the end ("equal time"); the other
    model's one row is both. A last row with the real motion's (``reference`` says which)."""
    extra = sorted({k for q in quality.values() for k in q} - {"jitter", "speed", "jps", "foot_skating"},
                   key=lambda k: (k != "fid", k))   # FID first
    lines = ["| model | steps | seconds | final loss | j/s (1/s²) | jitter (m/s³) | speed (m/s) | foot skating |"
             + "".join(f" {k} |" for k in extra),
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |" + " ---: |" * len(extra)]
    eq = train["equal_steps"]

    def cells(q: Dict[str, float]) -> str:
        return (f"{q['jps']:.0f} | {q['jitter']:.0f} | {q['speed']:.2f} | {q['foot_skating']:.3f} |"
                + "".join(f" {q[k]:.3f} |" if k in q else " — |" for k in extra))

    for key in quality:
        if key == "motion capture":
            continue
        if key.endswith("_equal_steps"):
            run = key[:-len("_equal_steps")]
            label, steps, secs, fl = f"{run}, equal steps", eq["steps"], eq["seconds"][run], eq["final_loss"][run]
        else:
            r = train[key]
            both = f"{key}_equal_steps" not in quality
            label = f"{key}, equal {'steps and time' if both else 'time'}"
            steps, secs, fl = r["steps"], r["seconds"], r["final_loss"]
        fl = "—" if fl is None else f"{fl:.4f}"
        lines.append(f"| {label} | {steps} | {secs:.1f} | {fl} | " + cells(quality[key]))
    lines.append(f"| motion capture ({reference}) | — | — | — | " + cells(quality["motion capture"]))
    return "\n".join(lines)


def save_models(trainers: Dict[str, Any], out: str, frames: int, mean: np.ndarray, std: np.ndarray,
                train: Dict[str, Any], clip_names: List[str], device: torch.device,
                equal_steps: Optional[Dict[str, Dict[str, torch.Tensor]]] = None) -> Dict[str, Any]:
    """Write ``out/dense`` and ``out/sparse`` (model folders ``smdm inbetween`` reads) and, for a
    model that trained on after the equal-steps point, ``out/<name>_equal_steps`` (its weights at
    that step, from ``equal_steps``); load them back."""
    from ...training.bundle import load_bundle, save_bundle
    from ...io.representation import Representation

    bundles = {}
    for n, tr in trainers.items():
        jobs = [(n, None, train[n]["steps"])]
        if equal_steps and n in equal_steps:
            jobs.insert(0, (f"{n}_equal_steps", equal_steps[n], train["equal_steps"]["steps"]))
        for folder, state, steps in jobs:
            current = None
            if state is not None:
                current = {k: v.detach().clone() for k, v in tr.model.state_dict().items()}
                tr.model.load_state_dict(state)
            save_bundle(os.path.join(out, folder), tr.model.eval(), tr.diffusion, tr.backbone_args,
                        Representation("joints66"), mean, std, fps=20, max_frames=frames, overwrite=True,
                        info={"trained_by": "smdm demo", "clips": clip_names, "steps": steps,
                              "world_size": train["world_size"]})
            if current is not None:
                tr.model.load_state_dict(current)
            bundles[folder] = load_bundle(os.path.join(out, folder), device=device)
    return bundles


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="smdm demo", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    args = p.parse_args(argv)
    if args.latent is not None and args.latent % 4:
        p.error(f"argument --latent: must be a multiple of 4 (the attention heads), got {args.latent}")
    first = os.environ.get("RANK", "0") == "0"  # under torchrun rank 0 checks (and alone writes)
    if first and os.path.isdir(args.out) and os.listdir(args.out) and not args.overwrite:
        p.error(f"argument --out: {args.out!r} exists and is not empty; pass --overwrite to write into it")
    if first and os.path.exists(args.out) and not os.path.isdir(args.out):
        p.error(f"argument --out: {args.out!r} exists and is not a folder")
    if args.evaluator is not None and args.no_evaluator:
        p.error("argument --no-evaluator: not allowed with argument --evaluator")
    if first and args.evaluator is not None:
        from .evaluator import load_demo_evaluator

        try:
            load_demo_evaluator(args.evaluator)
        except (ValueError, FileNotFoundError) as e:
            p.error(f"argument --evaluator: {' '.join(str(e).split())}")
    if not first:
        return main_demo(args)
    from ...io.outdir import run_in_output_dir  # locked, apart from the inputs, swapped in as one unit

    def write(part: str) -> int:  # main_demo writes into the partial folder; args.folder: where it ends up
        return main_demo(argparse.Namespace(**{**vars(args), "out": part, "folder": args.out}))

    inputs = {f"--bvh {b}": b for b in args.bvh or ()}
    if args.evaluator is not None:
        inputs["--evaluator"] = args.evaluator
    return run_in_output_dir(write, args.out, args.overwrite, inputs, "smdm demo")


if __name__ == "__main__":
    sys.exit(main())
