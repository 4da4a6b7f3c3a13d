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

from ..io.validate import load_feature_motion
from .common.args import note_printer, progress_of

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
    from ..metrics.evaluator.protocol import EVAL_MODES, PROTOCOLS
    from .common.args import add_common_flags, add_overwrite, existing_path, int_range, output_path, seed_type

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
    p.add_argument("--protocol", choices=PROTOCOLS, default="upstream",
                   help="upstream (default): per replication, shuffled drop-last draws of 32 motions with a random "
                        "caption and crop each, FID against another such draw of the real motions, as MDM's "
                        "eval_humanml; fixed: every motion, offset 0, FID against all real motions (0.4's)")
    p.add_argument("--eval-mode", choices=tuple(EVAL_MODES), default="wo_mm",
                   help="upstream's eval modes: replications (debug 5, wo_mm 20, mm_short 5, full 20) and whether "
                        "multimodality runs (mm_short, full) (default: wo_mm)")
    p.add_argument("--replications", type=int_range(1, 1000), default=None,
                   help="replications for the interval (default: --eval-mode's; with --protocol fixed: 3 with "
                        "--model, 1 with --motions)")
    p.add_argument("--mm-repeats", type=int_range(0, 1000), default=None,
                   help="with --model: generations per caption for multimodality, over --mm-captions captions "
                        "(0: off; default 11 when --eval-mode has multimodality or --protocol is fixed, else 0; "
                        "T2M: 30)")
    p.add_argument("--mm-captions", type=int_range(1, 100000), default=None,
                   help="with --model: captions multimodality runs on (default 10, T2M: 100)")
    p.add_argument("--inbetween-every", type=int_range(0, 10000), default=0, metavar="K",
                   help="with --model: in-betweening; every motion passes through the real motion's frames 0, K, "
                        "2K, ... and its last frame, and keyframe_error (m, joints) is reported (default 0: off)")
    p.add_argument("--out", required=True, metavar="RDIR", type=output_path(), help="results folder to write")
    add_overwrite(p)
    p.add_argument("--seed", type=seed_type, default=0,
                   help="seed of the caption draws, the generation noise and T2M's random pairs (default 0)")
    add_common_flags(p)  # --no-progress: no per-replication lines; --quiet: no header line either
    return p


def load_motion_folder(folder: str, ids: List[str], dim: int) -> List[np.ndarray]:
    """``folder/<id>.npy`` for every id, each ``[L, dim]`` finite with ``L >= 4``; ValueError naming the
    missing ids or the first bad file."""
    missing = [i for i in ids if not os.path.isfile(os.path.join(folder, f"{i}.npy"))]
    if missing:
        raise ValueError(f"--motions {folder!r}: missing {len(missing)} of {len(ids)} motions "
                         f"({', '.join(m + '.npy' for m in missing[:3])}{', ...' if len(missing) > 3 else ''})")
    return [load_feature_motion(os.path.join(folder, f"{i}.npy"), dim) for i in ids]


class Generator:
    """A model folder that generates raw features for given lengths and captions, sampled as the model
    is used: ``smdm train``'s (``model*.pt``, HumanML3D 263-D; with ``text_encoder.json`` it is
    text-conditioned and is sampled with each motion's caption and the saved classifier-free guidance
    scale) or a bundle (``motion.json``: ``smdm demo``'s, unconditional, any representation)."""

    def __init__(self, folder: str, device) -> None:
        import json

        from ..reference.simple_diffusion import SimpleDiffusion
        from ..reference.text import load_text_config

        self.device = device
        self.text = None      # the hashed bag-of-words conditioning of smdm train --text (text_encoder.json)
        self.swapped = None   # or the id of a swapped-in transformers encoder (the model reads y["text"])
        if os.path.isfile(os.path.join(folder, "motion.json")):
            from ..training.bundle import load_bundle

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
        # either layout: text_encoder.json beside the weights (smdm train --text), or a swapped encoder
        self.text = load_text_config(folder)
        if self.text is None:
            from ..adapters.text_encoder import swapped_text_encoder

            self.swapped = swapped_text_encoder(self.model)

    @property
    def conditioning(self) -> str:
        """How it is sampled, for tables: ``unconditional`` or the text encoder and guidance scale."""
        if self.text is not None:
            return f"text ({self.text.encoder}, guidance {self.text.guidance_scale:g})"
        if self.swapped is not None:
            return f"text (swapped encoder {self.swapped}, no guidance scale saved: none)"
        return "unconditional"

    def generate(self, lengths: List[int], seed: int, batch: int = 64, targets: Optional[List[np.ndarray]] = None,
                 every: int = 0, texts: Optional[List[str]] = None) -> List[np.ndarray]:
        """One motion ``[L_i, D]`` (raw features) per length (cut to the model's ``max_frames``), a
        text-conditioned model with ``texts[i]`` (required then); with ``targets`` (raw ``[L_i, D]``)
        and ``every`` > 0, in-betweening: each passes through its target's :func:`keyframe_frames`
        (``smdm_plugin.sample_inbetween``)."""
        import torch

        from ..reference.text import guided, sample_with_text, text_condition

        if (self.text is not None or self.swapped is not None) and (texts is None or len(texts) != len(lengths)):
            raise ValueError(f"a text-conditioned model needs one caption per motion, got "
                             f"{'none' if texts is None else len(texts)} for {len(lengths)}")
        out: List[np.ndarray] = []
        gen = torch.Generator(device=self.device).manual_seed(seed)
        mean, std = torch.from_numpy(self.mean), torch.from_numpy(self.std)
        fn = self.model if self.text is None else guided(self.model, self.text)
        for s in range(0, len(lengths), batch):
            L = torch.tensor([min(int(v), self.max_frames) for v in lengths[s:s + batch]])
            N = int(L.max())
            cap = None if self.text is None else list(texts[s:s + batch])
            raw = {"text": list(texts[s:s + batch])} if self.swapped is not None else {}
            with torch.no_grad():
                if targets is not None and every > 0:
                    from ..adapters.inbetween_sampling import keyframe_constraint, sample_inbetween

                    tgt = torch.zeros(len(L), N, len(self.mean))
                    for i, t in enumerate(targets[s:s + batch]):
                        tgt[i, :int(L[i])] = (torch.from_numpy(t[:int(L[i])]) - mean) / std
                    frames = keyframe_frames(L, N, every)
                    c = keyframe_constraint(tgt.to(self.device), frames.to(self.device), L.to(self.device))
                    ty = raw if cap is None else text_condition(self.text, cap, self.device)
                    x = sample_inbetween(fn, self.diffusion, c, y=ty or None, generator=gen)
                elif cap is not None:
                    x = sample_with_text(self.model, self.diffusion, self.text, cap, L, N, self.device, gen)
                    x = x.squeeze(2).permute(0, 2, 1)
                else:
                    y = {"mask": (torch.arange(N)[None] < L[:, None]).view(len(L), 1, 1, N).to(self.device),
                         "lengths": L.to(self.device), **raw}
                    x = self.diffusion.p_sample_loop(fn, (len(L), len(self.mean), 1, N), {"y": y},
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
    lines.append("| real (the split itself) | " + " | ".join(cell(real.get(k), f, real.get("fid_interval") if k == "fid"
                                                                   else None) for k, _, f in COLUMNS) + " |")
    fixed = protocol.get("name") == "fixed"
    notes = [f"{R} replication(s): mean ± 1.96·std/√R." if R > 1 else "1 replication (no interval).",
             ("Protocol fixed: every motion of the split, offset 0, FID against all of them (the real row's FID is 0 "
              "by construction)." if fixed else
              f"Protocol upstream (MDM's eval_humanml, eval mode {protocol.get('eval_mode')}): per replication a "
              f"reference draw and a scored draw of {protocol['pool_size']} motions (shuffled, drop-last), random "
              "caption and crop each; the real row's FID is the real-vs-real floor, what a perfect generator "
              "scores."),
             f"R-precision and matching score: batches of {protocol['pool_size']} motions ({protocol['n_scored']} of "
             f"{protocol['n_real']} scored; chance top-1 = {1 / protocol['pool_size']:.3f})"
             + ("; fewer than 32 motions: one batch of all, easier than the field's 32." if protocol['pool_size'] < 32
                else "."),
             f"Diversity: {protocol['diversity_times']} pairs (T2M: 300)." + (
                 f" Multimodality: {protocol['multimodality_times']} pairs." if protocol.get("multimodality_times") else ""),
             f"Evaluator: {protocol['evaluator']}."]
    return "\n".join(lines) + "\n\n" + "\n".join(f"* {n}" for n in notes) + "\n"


def sensitivity_note(folder: str, ev: Any) -> str:
    """What the evaluator can resolve, for the table: its saved sensitivity table (``smdm evaluator
    check``), or a line saying there is none or it does not fit the weights."""
    from ..metrics.evaluator.check import load_check

    try:
        table = load_check(folder, ev)
    except ValueError as e:
        return f"\n**Evaluator sensitivity:** not shown: {e}\n"
    if table is None:
        return ("\n**Evaluator sensitivity:** unknown; `smdm evaluator check EDIR --data DIR` measures what this "
                "evaluator resolves (noise, smoothing, time reversal, foot sliding, caption swap).\n")
    return (f"\n**Evaluator sensitivity** (`{os.path.join(folder, 'sensitivity.json')}`, on {table.data} "
            f"{table.split}): what a degradation of the real motions scores, beside the real floor.\n\n"
            + table.markdown())


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
    from ..metrics.evaluator.model import evaluator_layout, feature_mismatch, load_evaluator
    from .common.args import resolve_device

    if a.inbetween_every and not a.model:
        p.error("argument --inbetween-every: needs --model (the motions are generated through the keyframes)")
    if a.protocol == "fixed" and a.eval_mode != p.get_default("eval_mode"):
        p.error(f"argument --eval-mode: upstream's eval modes are --protocol upstream's; --protocol fixed has no use "
                "for it (--replications, --mm-repeats set its runs)")
    for option, value in (("--mm-repeats", a.mm_repeats), ("--mm-captions", a.mm_captions)):
        if value and not a.model:   # multimodality generates several motions per caption
            p.error(f"argument {option}: needs --model (multimodality generates several motions per caption)")
    from ..metrics.evaluator.protocol import EVAL_MODES

    if a.mm_repeats == 1:
        p.error("argument --mm-repeats: must be 0 (off) or >= 2 (multimodality compares generations of one caption), "
                "got 1")
    mm_off = a.mm_repeats == 0 or (a.mm_repeats is None and a.protocol != "fixed" and not EVAL_MODES[a.eval_mode][1])
    if a.model and a.mm_captions is not None and mm_off:
        p.error("argument --mm-captions: multimodality is off (--mm-repeats 0, or --eval-mode wo_mm / debug without "
                "--mm-repeats); give --mm-repeats N >= 2 or --eval-mode mm_short / full")
    if a.mm_captions is None:
        a.mm_captions = 10

    if not a.model and EVAL_MODES[a.eval_mode][1]:
        print(f"smdm eval: warning: --eval-mode {a.eval_mode}'s multimodality needs --model: with --motions it is "
              "not measured (its replications apply)", file=sys.stderr)
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
    why = feature_mismatch(ev, layout, real.representation, D)
    if why:
        p.error(f"argument --evaluator: {why}, the data ({a.data or 'embedded clips'}) has {real.representation} [{D}]")
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
        note_printer(a)(f"outputs: {os.path.abspath(a.out)}")
    return status


def _evaluate(a: argparse.Namespace, folder: str, dev: Any, real: Any, layout: str, ev: Any,
              gen_model: Optional[Generator], given: Optional[List[np.ndarray]]) -> int:
    """Score the motions (``given``, or ``gen_model``'s for ``a.replications``) and write
    :data:`OUTPUT_FILES` into ``folder`` (the partial folder of ``--out``); returns 0."""
    from ..io.files import atomic_write_json, atomic_write_text
    from ..metrics.evaluator.model import evaluator_info
    from ..metrics.evaluator.score import embed_captions, embed_motions, motion_quality, score_embeddings

    from ..metrics.evaluator.protocol import EVAL_MODES, replication

    fixed = a.protocol == "fixed"
    mode_reps, mode_mm = EVAL_MODES[a.eval_mode]
    R = a.replications or ((3 if a.model else 1) if fixed else mode_reps)
    mm_repeats = a.mm_repeats if a.mm_repeats is not None else (11 if (fixed or mode_mm) else 0)
    label = (f"{gen_model.label} model" if gen_model else "motions") + f" ({os.path.basename(os.path.normpath(a.model or a.motions))})"
    how = f", sampled {gen_model.conditioning}" if gen_model else ""
    say, progress = note_printer(a), progress_of(a)
    say(f"smdm eval: {len(real)} {a.split} motions from {a.data or 'the embedded CMU clips'}; evaluator "
          f"{layout} ({a.evaluator}); {label}{how}; {R} replication(s) of the {a.protocol} protocol on {dev}", flush=True)
    lengths = [len(m) for m in real.motions]
    ncap = [len(c) for c in real.captions]
    rows: List[Dict[str, Any]] = []
    res = None
    for r in range(R):
        seed = a.seed * 1000 + r
        rep = replication(a.protocol, lengths, ncap, seed=seed)
        real_emb = embed_motions(ev, rep.reference.motions(real.motions))
        scored = rep.scored.motions(real.motions)
        caps = rep.scored.captions(real.captions)
        if given is not None:  # a motion per id, its first frames up to the drawn length (as a model generates it)
            motions = [given[i][:n] for i, n in zip(rep.scored.index, rep.scored.length)]
        else:
            motions = gen_model.generate([len(m) for m in scored], seed=seed, texts=[c.text for c in caps],
                                         targets=scored if a.inbetween_every else None, every=a.inbetween_every)
        text = embed_captions(ev, [c.tokens for c in caps])
        mm = None
        if gen_model is not None and mm_repeats >= 2:
            k = min(a.mm_captions, len(scored))
            mm = np.stack([embed_motions(ev, gen_model.generate([len(scored[c])] * mm_repeats,
                                                                seed=seed * 100003 + c + 1,
                                                                texts=[caps[c].text] * mm_repeats))
                           for c in range(k)])
        res = score_embeddings(real_emb, text, embed_motions(ev, motions), mm, seed=seed,
                               scored_real=None if fixed else embed_motions(ev, scored))
        q = motion_quality(motions, fps=real.fps, representation=real.representation)
        if gen_model is not None and a.inbetween_every:
            q["keyframe_error"] = inbetween_error(motions, scored, a.inbetween_every, real.representation)
        rows.append({**res.to_dict(), **q})
        if progress:
            print(f"  replication {r + 1}/{R}: FID {res.fid:.3f} (real {res.real_fid:.3f}), R-precision top-3 "
                  f"{res.r_precision_top3:.3f} (real {res.real_r_precision_top3:.3f}), diversity {res.diversity:.3f}, "
                  f"jitter {q['jitter']:.1f} m/s³", flush=True)
    metrics = {k: _summary([row.get(k) for row in rows]) for k, _, _ in COLUMNS}
    rq = motion_quality(real.motions, fps=real.fps, representation=real.representation)
    # the real row: the real motions of the scored draws with the same captions and pairs, averaged over the
    # replications; its FID (the real-vs-real floor) with its interval
    real_keys = ("fid", "r_precision_top1", "r_precision_top2", "r_precision_top3", "matching_score", "diversity")
    real_row = {**{k: float(np.mean([row[f"real_{k}"] for row in rows])) for k in real_keys},
                "multimodality": None, **rq, "keyframe_error": None}
    real_row["fid_interval"] = _summary([row["real_fid"] for row in rows])["interval"]
    protocol = {"name": a.protocol, "eval_mode": None if fixed else a.eval_mode,
                "pool_size": res.pool_size, "n_scored": res.n_scored, "n_real": res.n_real,
                "n_generated": res.n_generated, "diversity_times": res.diversity_times,
                "multimodality_times": res.multimodality_times,
                "evaluator": f"{layout} ({os.path.abspath(a.evaluator)})",
                "sampling": gen_model.conditioning if gen_model else None,
                "caption": "one random caption per motion per replication (seeded)",
                "motion_reading": ("first min(L, 196) frames rounded down to a multiple of 4, zero-padded to 196; FID "
                                   "against all real motions" if fixed else
                                   "per replication, two shuffled drop-last draws of 32: a reference draw (FID's real "
                                   "statistics) and a scored draw (captions, lengths, the real row), each motion "
                                   "cropped at random as upstream's loader (min(L, 196) rounded down to a multiple of "
                                   "4, a third of the time 4 frames shorter, random offset)")}
    out = {"metrics": metrics, "real": real_row, "protocol": protocol, "replications": R, "rows": rows,
           "source": {"motions": a.motions and os.path.abspath(a.motions), "model": a.model and os.path.abspath(a.model),
                      "data": os.path.abspath(a.data) if a.data else "embedded CMU clips", "split": a.split,
                      "seed": a.seed, "mm_repeats": mm_repeats if a.model else 0,
                      "mm_captions": a.mm_captions if a.model else 0},
           "evaluator_info": {k: v for k, v in evaluator_info(a.evaluator).items() if k != "history"}}
    for k, _, _ in COLUMNS:  # flat means for readers that want one number per metric
        out[k] = metrics[k]["mean"]
    atomic_write_json(os.path.join(folder, "metrics.json"), out)
    table = markdown(metrics, real_row, label, R, protocol)
    if gen_model is not None and gen_model.text is None:
        table += ("* The model is unconditional (trained without text): its R-precision and matching score measure "
                  "how close its motions are to the split's captions, not text conditioning.\n")
    elif gen_model is not None:
        table += (f"* Sampled as the model is used: each motion from its drawn caption, {gen_model.conditioning}.\n")
    table += sensitivity_note(a.evaluator, ev)
    atomic_write_text(os.path.join(folder, "metrics.md"), table)
    plot(metrics, real_row, label.split(" (")[0], os.path.join(folder, "metrics.png"))
    print("\n" + table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
