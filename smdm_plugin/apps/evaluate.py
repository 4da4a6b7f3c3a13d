"""``smdm eval``: the field's text-to-motion metrics (FID, R-precision top-1/2/3, matching score,
diversity, multimodality) with a T2M evaluator of either source, plus jitter, jitter per unit speed
and foot skating, for a folder of motions or for a model that generates them.

    smdm eval --data DIR --evaluator EDIR --motions MDIR --out RDIR     # MDIR/<id>.npy, one per id of --split
    smdm eval --data DIR --evaluator EDIR --model MODEL --out RDIR --replications 3

Writes ``RDIR/metrics.json`` (each metric's replications, mean and 95% interval
``1.96 * std / sqrt(R)`` as the field reports them, the real motions' row, the protocol: pool size,
motions scored, diversity pairs), ``RDIR/metrics.md`` and ``RDIR/metrics.png``.
"""
from __future__ import annotations

import argparse
import os
import sys
from typing import Any, Dict, List, Optional

import numpy as np

from .common.threads import THREADS_HELP

#: metrics.json keys, in table order: (key, label, format)
COLUMNS = (("fid", "FID ↓", ".3f"), ("r_precision_top1", "R-prec. top-1 ↑", ".3f"),
           ("r_precision_top2", "top-2 ↑", ".3f"), ("r_precision_top3", "top-3 ↑", ".3f"),
           ("matching_score", "matching score ↓", ".3f"), ("diversity", "diversity →", ".3f"),
           ("multimodality", "multimodality ↑", ".3f"), ("jitter", "jitter (m/s³)", ".1f"),
           ("jitter_per_speed", "jitter / speed (1/s²)", ".1f"), ("foot_skating", "foot skating ↓", ".3f"),
           ("keyframe_error", "keyframe error (m) ↓", ".4f"))
#: what ``smdm eval`` writes into ``--out`` (``--overwrite`` replaces these, nothing else)
OUTPUT_FILES = ("metrics.json", "metrics.md", "metrics.png")



def build_parser() -> argparse.ArgumentParser:
    from .common.args import add_overwrite, device_type, existing_path, int_range

    p = argparse.ArgumentParser(prog="smdm eval", description=__doc__.split("\n\n")[0],
                                epilog="example: smdm eval --data dataset/HumanML3D --evaluator checkpoints "
                                       "--model runs/smdm --out results/smdm")
    p.add_argument("--data", type=existing_path("dir"), default=None, metavar="DIR",
                   help="HumanML3D-format folder with texts/ (default: the embedded CMU clips, as smdm evaluator "
                        "train reads them)")
    p.add_argument("--split", default="test", help="the real motions and captions scored against (default: test)")
    p.add_argument("--evaluator", required=True, type=existing_path("dir"), metavar="EDIR",
                   help="an evaluator folder: trained here (evaluator.json) or upstream's (finest.tar, glove/, "
                        "t2m_mean.npy / t2m_std.npy)")
    p.add_argument("--glove", type=existing_path("dir"), default=None, metavar="DIR",
                   help="GloVe folder for upstream's evaluator when it is not EDIR/glove")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--motions", type=existing_path("dir"), metavar="MDIR",
                     help="folder of <id>.npy raw feature motions [L, D], one per id of --split")
    src.add_argument("--model", type=existing_path("dir"), metavar="MODEL",
                     help="a model folder (smdm train --out, or smdm demo's DIR/dense, DIR/sparse) to generate from")
    p.add_argument("--replications", type=int_range(1, 1000), default=None,
                   help="generations of the whole split for the interval (default: 3 with --model, 1 with --motions)")
    p.add_argument("--mm-repeats", type=int_range(0, 1000), default=11,
                   help="with --model: generations per caption for multimodality, over --mm-captions captions "
                        "(0: off; default 11, T2M: 30)")
    p.add_argument("--mm-captions", type=int_range(1, 100000), default=10, help="(default 10, T2M: 100)")
    p.add_argument("--inbetween-every", type=int_range(0, 10000), default=0, metavar="K",
                   help="with --model: in-betweening; every motion passes through the real motion's frames 0, K, "
                        "2K, ... and its last frame, and keyframe_error (m, joints) is reported (default 0: off)")
    p.add_argument("--out", required=True, metavar="RDIR", help="results folder to write")
    add_overwrite(p)
    p.add_argument("--seed", type=int_range(0), default=0,
                   help="seed of the caption draws, the generation noise and T2M's random pairs (default 0)")
    p.add_argument("--device", type=device_type, default="auto", help="auto (CUDA, else MPS, else CPU), cpu, cuda, mps")
    p.add_argument("--threads", type=int_range(1, 1024), default=None, help=THREADS_HELP)
    return p


def load_motion_folder(folder: str, ids: List[str], dim: int) -> List[np.ndarray]:
    """``folder/<id>.npy`` for every id, each ``[L, dim]`` finite with ``L >= 4``; ValueError naming the
    missing ids or the first bad file."""
    missing = [i for i in ids if not os.path.isfile(os.path.join(folder, f"{i}.npy"))]
    if missing:
        raise ValueError(f"--motions {folder!r}: missing {len(missing)} of {len(ids)} motions "
                         f"({', '.join(m + '.npy' for m in missing[:3])}{', ...' if len(missing) > 3 else ''})")
    out = []
    for i in ids:
        path = os.path.join(folder, f"{i}.npy")
        try:
            m = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise ValueError(f"{path}: not a numpy array file ({e})") from None
        if m.ndim != 2 or m.shape[1] != dim or len(m) < 4 or not np.issubdtype(m.dtype, np.floating):
            raise ValueError(f"{path}: expected raw features [L >= 4, {dim}] float, got {m.shape} {m.dtype}")
        if not np.isfinite(m).all():
            raise ValueError(f"{path}: has non-finite values")
        out.append(m.astype(np.float32))
    return out


class Generator:
    """A model folder that generates raw features for given lengths: ``smdm train``'s (``model*.pt``,
    HumanML3D 263-D) or a bundle (``motion.json``: ``smdm demo``'s, any representation)."""

    def __init__(self, folder: str, device) -> None:
        import json

        from ..reference.diffusion import SimpleDiffusion

        self.device = device
        if os.path.isfile(os.path.join(folder, "motion.json")):
            from ..io.bundle import load_bundle

            b = load_bundle(folder, device=device)
            self.model, self.diffusion, self.mean, self.std = b.model, b.diffusion, b.mean, b.std
            self.representation, self.max_frames, self.label = b.representation.name, b.max_frames, b.label
        else:
            from ..training.trainer import TRAIN_CONFIG_FILENAME, load_trained

            model, config = load_trained(folder, map_location="cpu")
            with open(os.path.join(folder, TRAIN_CONFIG_FILENAME)) as f:
                tc = json.load(f)
            self.model = model.to(device).eval()
            self.diffusion = SimpleDiffusion(int(tc["diffusion_steps"]))
            self.mean = np.load(os.path.join(folder, "Mean.npy")).astype(np.float32)
            self.std = np.load(os.path.join(folder, "Std.npy")).astype(np.float32)
            self.representation = "humanml3d" if len(self.mean) == 263 else "raw"
            self.max_frames = int(tc.get("max_frames", 196))
            self.label = "sparse" if config is not None else "dense"

    def generate(self, lengths: List[int], seed: int, batch: int = 64, targets: Optional[List[np.ndarray]] = None,
                 every: int = 0) -> List[np.ndarray]:
        """One motion ``[L_i, D]`` (raw features) per length (cut to the model's ``max_frames``); with
        ``targets`` (raw ``[L_i, D]``) and ``every`` > 0, in-betweening: each passes through its
        target's :func:`keyframe_frames` (``smdm_plugin.sample_inbetween``)."""
        import torch

        out: List[np.ndarray] = []
        gen = torch.Generator(device=self.device).manual_seed(seed)
        mean, std = torch.from_numpy(self.mean), torch.from_numpy(self.std)
        for s in range(0, len(lengths), batch):
            L = torch.tensor([min(int(v), self.max_frames) for v in lengths[s:s + batch]])
            N = int(L.max())
            with torch.no_grad():
                if targets is not None and every > 0:
                    from ..adapters.inbetween import keyframe_constraint, sample_inbetween

                    tgt = torch.zeros(len(L), N, len(self.mean))
                    for i, t in enumerate(targets[s:s + batch]):
                        tgt[i, :int(L[i])] = (torch.from_numpy(t[:int(L[i])]) - mean) / std
                    frames = keyframe_frames(L, N, every)
                    c = keyframe_constraint(tgt.to(self.device), frames.to(self.device), L.to(self.device))
                    x = sample_inbetween(self.model, self.diffusion, c, generator=gen)
                else:
                    y = {"mask": (torch.arange(N)[None] < L[:, None]).view(len(L), 1, 1, N).to(self.device),
                         "lengths": L.to(self.device)}
                    x = self.diffusion.p_sample_loop(self.model, (len(L), len(self.mean), 1, N), {"y": y},
                                                     device=self.device, generator=gen)
                    x = x.squeeze(2).permute(0, 2, 1)
            feats = x.float().cpu().numpy() * self.std + self.mean
            out += [feats[i, :int(L[i])] for i in range(len(L))]
        return out


def keyframe_frames(lengths, N: int, every: int):
    """bool ``[B, N]``: frames ``0, every, 2 every, ...`` and the last valid frame of each motion."""
    import torch

    idx = torch.arange(N)[None]
    return ((idx % every == 0) | (idx == lengths[:, None] - 1)) & (idx < lengths[:, None])


def inbetween_error(motions: List[np.ndarray], targets: List[np.ndarray], every: int, representation: str) -> float:
    """Mean joint position error (m) at :func:`keyframe_frames` between each motion and its target."""
    import torch

    from ..io.representation import Representation
    from ..metrics.evaluator.score import as_padded
    from ..metrics.quality import keyframe_error

    x, L = as_padded(motions)
    t, _ = as_padded([m[:len(g)] for m, g in zip(targets, motions)])
    rep = Representation(representation)
    return float(keyframe_error(torch.as_tensor(rep.to_joints(x)), torch.as_tensor(rep.to_joints(t)),
                                keyframe_frames(L, x.shape[1], every), lengths=L))


def _summary(values: List[Optional[float]]) -> Dict[str, Any]:
    from ..metrics.t2m import mean_interval

    vals = [v for v in values if v is not None and np.isfinite(v)]
    if not vals:
        return {"mean": None, "interval": None, "values": values}
    m, ci = mean_interval(vals)
    return {"mean": m, "interval": ci, "values": values}


def markdown(metrics: Dict[str, Dict[str, Any]], real: Dict[str, Any], label: str, R: int, protocol: Dict[str, Any]
             ) -> str:
    head = "| motions | " + " | ".join(c[1] for c in COLUMNS) + " |"
    lines = [head, "|" + " --- |" * (len(COLUMNS) + 1)]

    def cell(v, fmt, ci=None):
        if v is None or (isinstance(v, float) and not np.isfinite(v)):
            return "—"
        return f"{v:{fmt}}" + (f" ± {ci:{fmt}}" if ci is not None and R > 1 else "")

    lines.append(f"| {label} | " + " | ".join(cell(metrics[k]["mean"], f, metrics[k]["interval"]) for k, _, f in COLUMNS)
                 + " |")
    lines.append("| real (the split itself) | " + " | ".join(cell(real.get(k), f) for k, _, f in COLUMNS) + " |")
    notes = [f"{R} replication(s): mean ± 1.96·std/√R." if R > 1 else "1 replication (no interval).",
             f"R-precision and matching score: batches of {protocol['pool_size']} motions ({protocol['n_scored']} of "
             f"{protocol['n_real']} scored; chance top-1 = {1 / protocol['pool_size']:.3f})"
             + ("; fewer than 32 motions: one batch of all, easier than the field's 32." if protocol['pool_size'] < 32
                else "."),
             f"Diversity: {protocol['diversity_times']} pairs (T2M: 300)." + (
                 f" Multimodality: {protocol['multimodality_times']} pairs." if protocol.get("multimodality_times") else ""),
             f"Evaluator: {protocol['evaluator']}."]
    return "\n".join(lines) + "\n\n" + "\n".join(f"* {n}" for n in notes) + "\n"


def plot(metrics: Dict[str, Dict[str, Any]], real: Dict[str, Any], label: str, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io.files import atomic_open

    keys = [c for c in COLUMNS if metrics[c[0]]["mean"] is not None]
    fig, axes = plt.subplots(1, len(keys), figsize=(2.0 * len(keys), 3.2))
    for ax, (k, name, _) in zip(np.atleast_1d(axes), keys):
        m = metrics[k]
        vals = [m["mean"], real.get(k)]
        errs = [m["interval"] or 0.0, 0.0]
        ok = [v is not None and np.isfinite(v) for v in vals]
        xs = [i for i in range(2) if ok[i]]
        ax.bar(xs, [vals[i] for i in xs], yerr=[errs[i] for i in xs], color=["tab:blue", "tab:gray"][:len(xs)],
               capsize=3)
        ax.set_xticks([0, 1])
        ax.set_xticklabels([label, "real"], rotation=30, fontsize=7)
        ax.set_title(name, fontsize=8)
        ax.tick_params(axis="y", labelsize=7)
    fig.tight_layout()
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=100)
    plt.close(fig)


def main(argv: Optional[List[str]] = None) -> int:
    p = build_parser()
    a = p.parse_args(argv)
    from ..io.files import OutputExistsError
    from ..io.outdir import OutputDir, run_in_output_dir
    from ..metrics.evaluator.data import load_split
    from ..metrics.evaluator.model import evaluator_layout, load_evaluator
    from .common.args import resolve_device

    if a.inbetween_every and not a.model:
        p.error("argument --inbetween-every: needs --model (the motions are generated through the keyframes)")
    from .common.threads import apply_threads

    apply_threads(a.threads)
    # locked for the run, apart from every input, written in a partial folder and swapped in as one unit
    out_kw = dict(overwrite=a.overwrite, command="smdm eval", owns=OUTPUT_FILES,
                  inputs={"--motions": a.motions, "--model": a.model, "--evaluator": a.evaluator, "--data": a.data,
                          "--glove": a.glove})
    try:
        OutputDir(a.out, **out_kw).check()  # refused before anything is loaded or written
    except OutputExistsError as e:
        print(f"smdm eval: error: {e}", file=sys.stderr)
        return 2
    dev = resolve_device(a.device)
    try:
        real = load_split(a.data, a.split)
        layout = evaluator_layout(a.evaluator)
        ev = load_evaluator(a.evaluator, glove=a.glove, device=dev)
    except (FileNotFoundError, ValueError) as e:
        print(f"smdm eval: {e}", file=sys.stderr)
        return 2
    D = real.motions[0].shape[1]
    if ev.config.dim_pose != D or (layout == "own" and ev.config.representation != real.representation):
        p.error(f"argument --evaluator: it reads {ev.config.representation} [{ev.config.dim_pose}] features, the "
                f"data ({a.data or 'embedded clips'}) has {real.representation} [{D}]")
    try:
        gen_model = Generator(a.model, dev) if a.model else None
        if gen_model is not None and len(gen_model.mean) != D:
            raise ValueError(f"--model {a.model!r} generates {len(gen_model.mean)}-D features, the data has {D}-D")
        given = load_motion_folder(a.motions, real.ids, D) if a.motions else None
    except (FileNotFoundError, ValueError) as e:
        print(f"smdm eval: {e}", file=sys.stderr)
        return 2
    status = run_in_output_dir(lambda folder: _evaluate(a, folder, dev, real, layout, ev, gen_model, given),
                               a.out, **out_kw)
    if status == 0:
        print(f"outputs: {os.path.abspath(a.out)}")
    return status


def _evaluate(a: argparse.Namespace, folder: str, dev: Any, real: Any, layout: str, ev: Any,
              gen_model: Optional[Generator], given: Optional[List[np.ndarray]]) -> int:
    """Score the motions (``given``, or ``gen_model``'s for ``a.replications``) and write
    :data:`OUTPUT_FILES` into ``folder`` (the partial folder of ``--out``); returns 0."""
    from ..io.files import atomic_write_json, atomic_write_text
    from ..metrics.evaluator.model import evaluator_info
    from ..metrics.evaluator.score import embed_captions, embed_motions, motion_quality, score_embeddings

    R = a.replications or (3 if a.model else 1)
    lengths = [len(m) for m in real.motions]
    label = (f"{gen_model.label} model" if gen_model else "motions") + f" ({os.path.basename(os.path.normpath(a.model or a.motions))})"
    print(f"smdm eval: {len(real)} {a.split} motions from {a.data or 'the embedded CMU clips'}; evaluator "
          f"{layout} ({a.evaluator}); {label}; {R} replication(s) on {dev}", flush=True)
    real_emb = embed_motions(ev, real.motions)
    rows: List[Dict[str, Any]] = []
    res = None
    for r in range(R):
        motions = given if given is not None else gen_model.generate(
            lengths, seed=a.seed * 1000 + r, targets=real.motions if a.inbetween_every else None,
            every=a.inbetween_every)
        text = embed_captions(ev, real.first_captions(seed=a.seed * 1000 + r))
        mm = None
        if gen_model is not None and a.mm_repeats >= 2:
            k = min(a.mm_captions, len(real))
            mm = np.stack([embed_motions(ev, gen_model.generate([lengths[c]] * a.mm_repeats,
                                                                seed=(a.seed * 1000 + r) * 100003 + c + 1))
                           for c in range(k)])
        res = score_embeddings(real_emb, text, embed_motions(ev, motions), mm, seed=a.seed * 1000 + r)
        q = motion_quality(motions, fps=real.fps, representation=real.representation)
        if gen_model is not None and a.inbetween_every:
            q["keyframe_error"] = inbetween_error(motions, real.motions, a.inbetween_every, real.representation)
        rows.append({**res.to_dict(), **q})
        print(f"  replication {r + 1}/{R}: FID {res.fid:.3f}, R-precision top-3 {res.r_precision_top3:.3f}, "
              f"diversity {res.diversity:.3f}, jitter {q['jitter']:.1f} m/s³", flush=True)
    metrics = {k: _summary([row.get(k) for row in rows]) for k, _, _ in COLUMNS}
    rq = motion_quality(real.motions, fps=real.fps, representation=real.representation)
    # the real row: the same caption draws and pairs as the generated rows, averaged over the replications
    real_row = {"fid": 0.0, **{k: float(np.mean([row[f"real_{k}"] for row in rows]))
                               for k in ("r_precision_top1", "r_precision_top2", "r_precision_top3", "matching_score",
                                         "diversity")}, "multimodality": None, **rq, "keyframe_error": None}
    protocol = {"pool_size": res.pool_size, "n_scored": res.n_scored, "n_real": res.n_real,
                "diversity_times": res.diversity_times, "multimodality_times": res.multimodality_times,
                "evaluator": f"{layout} ({os.path.abspath(a.evaluator)})",
                "caption": "one random caption per motion per replication (seeded)",
                "motion_reading": "first min(L, 196) frames rounded down to a multiple of 4, zero-padded to 196"}
    out = {"metrics": metrics, "real": real_row, "protocol": protocol, "replications": R, "rows": rows,
           "source": {"motions": a.motions and os.path.abspath(a.motions), "model": a.model and os.path.abspath(a.model),
                      "data": os.path.abspath(a.data) if a.data else "embedded CMU clips", "split": a.split,
                      "seed": a.seed, "mm_repeats": a.mm_repeats if a.model else 0,
                      "mm_captions": a.mm_captions if a.model else 0},
           "evaluator_info": {k: v for k, v in evaluator_info(a.evaluator).items() if k != "history"}}
    for k, _, _ in COLUMNS:  # flat means for readers that want one number per metric
        out[k] = metrics[k]["mean"]
    atomic_write_json(os.path.join(folder, "metrics.json"), out)
    table = markdown(metrics, real_row, label, R, protocol)
    if gen_model is not None:
        table += ("* The in-package TinyMDM is trained without text: its R-precision and matching score measure how "
                  "close its motions are to the split's captions, not text conditioning.\n")
    atomic_write_text(os.path.join(folder, "metrics.md"), table)
    plot(metrics, real_row, label.split(" (")[0], os.path.join(folder, "metrics.png"))
    print("\n" + table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
