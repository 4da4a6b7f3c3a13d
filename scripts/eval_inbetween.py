"""Keyframe in-betweening on held-out real motion: train dense and sparse in-package models, then
measure keyframe error and transition smoothness (docs/inbetween.md).

    python scripts/eval_inbetween.py train --out results/inbetween [--steps 3000] [--rep joints66 humanml3d]
    python scripts/eval_inbetween.py eval  --out results/inbetween [--seeds 2]

Data: ``../shared/data/cmu-humanml3d`` (``--data``): the train split trains, val + test evaluate.
``train`` writes model folders ``OUT/models/<rep>-<dense|sparse>`` (``smdm inbetween --model`` reads
them) and ``OUT/models/<rep>-training.json``; ``eval`` writes ``OUT/results.json`` and ``OUT/results.md``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Tuple

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
DEFAULT_DATA = HERE.parent.parent / "shared" / "data" / "cmu-humanml3d"  # ../shared beside the repository
FRAMES = 196


def split_ids(data: Path, splits: List[str]) -> List[str]:
    return [i for s in splits for i in (data / f"{s}.txt").read_text().split()]


def load_motions(data: Path, rep: str, ids: List[str]) -> List[np.ndarray]:
    """HumanML3D features ``[T, 263]`` or joints ``[T, 22, 3]`` per id."""
    folder = "new_joint_vecs" if rep == "humanml3d" else "new_joints"
    return [np.load(data / folder / f"{i}.npy").astype(np.float32) for i in ids]


def transform_for(rep: str):
    from smdm_plugin.io.representation import canonical_xz, joints_to_joints66

    if rep == "humanml3d":
        return lambda m: m
    return lambda m: joints_to_joints66(canonical_xz(m))


def stats_for(data: Path, rep: str, motions: List[np.ndarray]) -> Tuple[np.ndarray, np.ndarray]:
    from smdm_plugin.training.data import feature_stats

    if rep == "humanml3d":  # the data set's own Mean/Std, as MDM normalises
        return np.load(data / "Mean.npy").astype(np.float32), np.load(data / "Std.npy").astype(np.float32)
    tf = transform_for(rep)
    return feature_stats([tf(m) for m in motions])


def heldout_loss(x: torch.Tensor, lengths: torch.Tensor, mean: np.ndarray, std: np.ndarray):
    """``validate(model, diffusion)``: the x0 MSE (normalised, valid frames) on the held-out motions at
    t = 0, T/5, T/2 (0, 10, 25 at T = 50) with fixed noise — reported while training, not used to pick a model."""
    xn = ((x - torch.from_numpy(mean)) / torch.from_numpy(std)).permute(0, 2, 1).unsqueeze(2)
    valid = (torch.arange(x.shape[1])[None] < lengths[:, None])
    y = {"mask": valid.view(-1, 1, 1, x.shape[1]), "lengths": lengths}
    noise = torch.randn(xn.shape, generator=torch.Generator().manual_seed(0))

    def validate(model, diffusion) -> float:
        errs = []
        T = diffusion.num_timesteps
        for t in sorted({0, T // 5, T // 2}):
            tt = torch.full((len(lengths),), t)
            x0 = model(diffusion.q_sample(xn, tt, noise), tt, y)
            errs.append(((x0 - xn) ** 2).mean(dim=(1, 2))[valid].mean())
        return float(torch.stack(errs).mean())
    return validate


def cmd_train(a: argparse.Namespace) -> int:
    """Train dense and sparse TinyMDM with the in-package Trainer on the train split (each motion's
    first 196 frames) and save them as model folders."""
    from smdm_plugin.training.data import MotionSet
    from smdm_plugin.training.trainer import TrainConfig, Trainer
    from smdm_plugin.core.config import SparseConfig
    from smdm_plugin.training.bundle import save_bundle
    from smdm_plugin.io.representation import Representation

    torch.set_num_threads(a.threads)
    data = Path(a.data)
    ids = split_ids(data, ["train"])
    for rep in a.rep:
        raw = load_motions(data, rep, ids)
        mean, std = stats_for(data, rep, raw)
        tf = transform_for(rep)
        kept = [(i, tf(m)) for i, m in zip(ids, raw) if len(m) >= a.min_frames]
        motions = MotionSet.from_motions([m for _, m in kept], mean, std, [i for i, _ in kept], FRAMES)
        model = {"latent_dim": a.latent, "ff_size": 2 * a.latent, "num_layers": a.layers, "num_heads": 4,
                 "dropout": a.dropout}
        print(f"[{rep}] {len(motions)} training motions, TinyMDM {model}", flush=True)
        _, xv, Lv = eval_set(data, rep)
        validate = heldout_loss(xv, Lv, mean, std)
        stats: Dict[str, Any] = {"model": model, "batch": a.batch, "seed": a.seed, "steps": a.steps}
        os.makedirs(os.path.join(a.out, "models"), exist_ok=True)
        for name, sc in (("dense", None), ("sparse", SparseConfig(reduction=a.reduction,
                                                                  feature="raw" if rep == "joints66" else "auto"))):
            trainer = Trainer(TrainConfig(steps=a.steps, batch=a.batch, lr=a.lr, diffusion_steps=a.diffusion_steps,
                                          seed=a.seed, model=model, sparse=sc), motions, device="cpu")
            val: List[Tuple[int, float]] = []

            def log(tr: Trainer, loss: float) -> None:
                if a.log_every and tr.step_count % a.log_every == 0:
                    tr.model.eval()
                    with torch.no_grad():
                        val.append((tr.step_count, float(validate(tr.model, tr.diffusion))))
                    tr.model.train()
                    print(f"{name} step {tr.step_count}: loss {np.mean(tr.losses[-a.log_every:]):.4f}, "
                          f"validation {val[-1][1]:.4f}", flush=True)

            result = trainer.train(progress=a.progress, callback=log)
            stats[name] = {**result.to_dict(), "val": val}
            print(f"[{rep}] {name}: final loss {result.final_loss:.4f}, {result.steps_per_s:.2f} steps/s", flush=True)
            save_bundle(os.path.join(a.out, "models", f"{rep}-{name}"), trainer.model.eval(), trainer.diffusion,
                        trainer.backbone_args, Representation(rep), mean, std, fps=20, max_frames=FRAMES,
                        info={"data": str(data), "split": "train", "motions": len(motions), "steps": a.steps,
                              "batch": a.batch, "seed": a.seed, "threads": a.threads},
                        overwrite=a.overwrite)
        stats["speed_ratio"] = stats["sparse"]["steps_per_s"] / stats["dense"]["steps_per_s"]
        with open(os.path.join(a.out, "models", f"{rep}-training.json"), "w") as f:
            json.dump(stats, f)
    return 0


# --------------------------------------------------------------------------- evaluation
TASKS = {
    "keyframes-1s": "a keyframe every 20 frames (1 s) and the last frame",
    "mdm-in-between": "MDM's edit in_between: the first 25% and the last 25% of the frames given",
}


def given_frames(task: str, lengths: torch.Tensor, N: int) -> torch.Tensor:
    """bool ``[B, N]``: the frames given as keyframes in ``task``."""
    g = torch.zeros(len(lengths), N, dtype=torch.bool)
    for b, L in enumerate(lengths.tolist()):
        if task == "keyframes-1s":
            g[b, list(range(0, L, 20)) + [L - 1]] = True
        else:  # as sample/edit.py: prefix_end=0.25, suffix_start=0.75
            g[b, :int(0.25 * L)] = True
            g[b, int(0.75 * L):L] = True
    return g


def eval_set(data: Path, rep: str) -> Tuple[List[str], torch.Tensor, torch.Tensor]:
    """Held-out motions (val + test): un-normalised features ``[B, 196, D]`` (joints66: each motion's
    root at x = z = 0 at frame 0) and lengths ``[B]``."""
    ids = split_ids(data, ["val", "test"])
    tf = transform_for(rep)
    motions = [tf(m) for m in load_motions(data, rep, ids)]
    x = torch.zeros(len(ids), FRAMES, motions[0].shape[-1])
    for b, m in enumerate(motions):
        x[b, :len(m)] = torch.from_numpy(np.asarray(m[:FRAMES], np.float32))
    return ids, x, torch.tensor([min(len(m), FRAMES) for m in motions])


def score(rep, out: torch.Tensor, ref: torch.Tensor, given: torch.Tensor, lengths: torch.Tensor) -> Dict[str, float]:
    """Metrics of generated features ``out [B, N, D]`` against the real motions ``ref`` (un-normalised)."""
    from smdm_plugin.metrics.inbetween_metrics import keyframe_metrics

    return {"feature_error": float((out - ref).abs()[given].max()),
            **keyframe_metrics(rep.to_joints(out.double()).numpy(), rep.to_joints(ref.double()).numpy(),
                               given.numpy(), lengths=lengths, reference=True)}


def cmd_eval(a: argparse.Namespace) -> int:
    from smdm_plugin.adapters.inbetween_sampling import keyframe_constraint, sample_inbetween
    from smdm_plugin.training.bundle import load_bundle

    torch.set_num_threads(a.threads)
    data = Path(a.data)
    path = os.path.join(a.out, "results.json")
    results: Dict[str, Any] = {"rows": [], "reference": {}}
    if os.path.exists(path):  # keep the rows of the representations not evaluated now
        with open(path) as f:
            results = json.load(f)
        results["rows"] = [r for r in results["rows"] if r["rep"] not in a.rep]
    results["settings"] = {**results.get("settings", {}), **{f"{rep}": vars(a) for rep in a.rep}}
    for rep in a.rep:
        ids, x, lengths = eval_set(data, rep)
        bundles = {n: load_bundle(os.path.join(a.out, "models", f"{rep}-{n}")) for n in ("dense", "sparse")}
        representation = bundles["dense"].representation
        for task in TASKS:
            given = given_frames(task, lengths, FRAMES)
            ref_scores = score(representation, x, x, given, lengths)
            results["reference"][f"{rep}/{task}"] = {k: ref_scores["reference_" + k] for k in (
                "jitter_transitions", "jitter", "foot_skating")}
            configs = [("dense", "x0", "ends"), ("sparse", "x0", "ends")]
            if task == "keyframes-1s":
                configs += [("dense", "xt", "ends"), ("sparse", "xt", "ends"), ("sparse", "x0", "none")]
            else:
                configs += [("sparse", "x0", "all"), ("sparse", "x0", "none")]
            for name, imputation, policy in configs:
                b = bundles[name]
                c = keyframe_constraint(b.normalise(x), given, lengths)
                outs, seconds = [], 0.0
                for seed in range(a.seeds):
                    t0 = time.perf_counter()
                    out = sample_inbetween(b.model, b.diffusion, c, imputation=imputation, policy=policy,
                                           generator=torch.Generator().manual_seed(seed))
                    seconds += time.perf_counter() - t0
                    outs.append(b.denormalise(out))
                scores = [score(representation, o, x, given, lengths) for o in outs]
                row = {"rep": rep, "task": task, "model": name, "imputation": imputation,
                       "forced": policy if name == "sparse" else "—", "seconds_per_batch": seconds / a.seeds,
                       **{k: float(np.mean([s[k] for s in scores])) for k in scores[0]},
                       **{k + "_std": float(np.std([s[k] for s in scores])) for k in scores[0]}}
                results["rows"].append(row)
                print(f"[{rep} {task}] {name} {imputation} {row['forced']}: kf {row['keyframe_error_mm']:.1f} mm, "
                      f"jitter@transitions {row['jitter_transitions']:.1f}, jitter {row['jitter']:.1f}, "
                      f"{row['seconds_per_batch']:.1f} s", flush=True)
    results["eval_ids"] = ids
    results["rows"].sort(key=lambda r: ["joints66", "humanml3d"].index(r["rep"]))
    with open(path, "w") as f:
        json.dump(results, f, indent=1)
    md = results_markdown(results)
    with open(os.path.join(a.out, "results.md"), "w") as f:
        f.write(md + "\n")
    print(md)
    return 0


def results_markdown(results: Dict[str, Any]) -> str:
    cols = (("keyframe feature error (max)", "feature_error", "{:.1g}"), ("keyframe error (mm)", "keyframe_error_mm", "{:.1f}"),
            ("root-rel. keyframe error (mm)", "keyframe_error_root_relative_mm", "{:.1f}"),
            ("jitter at transitions (m/s³)", "jitter_transitions", "{:.0f}"), ("jitter (m/s³)", "jitter", "{:.0f}"),
            ("foot skating", "foot_skating", "{:.3f}"), ("in-between error (mm)", "inbetween_error_mm", "{:.0f}"),
            ("sampling (s / batch)", "seconds_per_batch", "{:.1f}"))
    out = []
    for rep_task in dict.fromkeys(f"{r['rep']}/{r['task']}" for r in results["rows"]):
        rep, task = rep_task.split("/")
        ref = results["reference"][rep_task]
        out += [f"**{rep}, {task}** ({TASKS[task]}); real motion: jitter at transitions {ref['jitter_transitions']:.0f}, "
                f"jitter {ref['jitter']:.0f} m/s³, foot skating {ref['foot_skating']:.3f}", "",
                "| model | imputation | forced keyframes | " + " | ".join(c[0] for c in cols) + " |",
                "| --- | --- | --- |" + " ---: |" * len(cols)]
        for r in results["rows"]:
            if f"{r['rep']}/{r['task']}" == rep_task:
                cells = [c[2].format(r[c[1]]) + (f" ± {c[2].format(r[c[1] + '_std'])}" if r.get(c[1] + "_std") and
                                                c[1] in ("jitter_transitions", "keyframe_error_mm") else "") for c in cols]
                out.append(f"| {r['model']} | {r['imputation']} | {r['forced']} | " + " | ".join(cells) + " |")
        out.append("")
    return "\n".join(out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--out", default="results/inbetween")
    common.add_argument("--data", default=str(DEFAULT_DATA))
    common.add_argument("--rep", nargs="+", default=["joints66", "humanml3d"], choices=["joints66", "humanml3d"])
    common.add_argument("--threads", type=int, default=1)
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", parents=[common])
    t.add_argument("--steps", type=int, default=3000)
    t.add_argument("--batch", type=int, default=16)
    t.add_argument("--latent", type=int, default=128)
    t.add_argument("--layers", type=int, default=4)
    t.add_argument("--lr", type=float, default=2e-4)
    t.add_argument("--reduction", type=float, default=0.8)
    t.add_argument("--diffusion-steps", type=int, default=50)
    t.add_argument("--min-frames", type=int, default=40)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--progress", action="store_true")
    t.add_argument("--dropout", type=float, default=0.1)
    t.add_argument("--log-every", type=int, default=250)
    t.add_argument("--overwrite", action="store_true")
    e = sub.add_parser("eval", parents=[common])
    e.add_argument("--seeds", type=int, default=2)
    a = p.parse_args(argv)
    return {"train": cmd_train, "eval": cmd_eval}[a.cmd](a)


if __name__ == "__main__":
    sys.exit(main())
