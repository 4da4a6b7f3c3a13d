"""The quality-versus-compute study: dense vs sparse variants trained to equal compute budgets and
equal step counts, text-conditioned, scored with a text-motion evaluator trained on the same data."""
from __future__ import annotations

import argparse
import csv
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from ...support.values import closest
from ...io.files import OutputExistsError, atomic_open, atomic_write_json, atomic_write_text
from ..common.args import (add_common_flags, add_overwrite, existing_path, note_printer, output_path, progress_of,
                           resolve_device)
from .results import (MANIFEST, check_out_dir, FAILED_FILE, RESULT_FILE, CacheState, Cached, Record, Status, failure_record, is_ok, read_cached,
                      status_of)
from .grid import (AblateConfigError, _check, _check_keys, check_variants, config_path, over_defaults, select_variants,
                   slug, sparse_config)
from ...io.files import fingerprint_files
from ..common.provenance import make_provenance, stable_hash
from .paired import reference_lines

KIND = "quality_compute"
DEFAULT_DATA = os.path.join("..", "shared", "data", "cmu-humanml3d-large")
DEFAULTS: Dict[str, Any] = {
    "name": KIND, "kind": KIND, "seeds": [0, 1, 2], "batch": 16, "max_frames": 120, "min_frames": 40,
    "diffusion_steps": 50, "lr": 3e-4,
    "model": {"latent_dim": 128, "num_layers": 2, "num_heads": 4, "ff_size": 256, "arch": "trans_enc", "dropout": 0.1},
    "text": {"encoder": "hashed_bow", "dim": 512, "seed": 0, "cond_mask_prob": 0.1, "guidance_scale": 2.5},
    "sparse": {"reduction": 0.8},
    "snapshots": {"steps": [100, 250], "seconds": [8.0, 16.0, 32.0]},
    "clock": "cpu",
    "eval": {"split": "test", "limit": None, "batch": 16},
    "evaluator": {"kind": "t2m"},
    "primary": {},
}
#: the settings that shape every run's result (with the variant, its SparseConfig and the evaluator key)
RUN_SETTINGS = ("batch", "max_frames", "min_frames", "diffusion_steps", "lr", "model", "text", "sparse", "snapshots",
                "clock", "eval")
METRICS = ("fid", "r_precision_top1", "r_precision_top2", "r_precision_top3", "matching_score", "diversity",
           "jitter", "speed", "jitter_per_speed", "foot_skating")
#: how a set is scored (part of every run's provenance: a change makes earlier results stale): R-precision
#: and matching score averaged over RETRIEVAL_DRAWS seeded pools of 32 of the evaluation motions; FID with
#: a bootstrap over the motions (FID_RESAMPLES resamples, generated motion i with caption i resampled together)
RETRIEVAL_DRAWS = 20
FID_RESAMPLES = 200
#: a (variant, seed) folder's checkpoint of an unfinished run (removed once its result is written)
CHECKPOINT_DIR = "checkpoint"
SCORING = f"retrieval mean of {RETRIEVAL_DRAWS} pools; FID bootstrap {FID_RESAMPLES} paired resamples"


# ----------------------------------------------------------------------------------------- config
def is_study_config(name_or_path: str) -> bool:
    """Whether the grid ``name_or_path`` is a quality-versus-compute study (``kind: quality_compute``)."""
    import yaml

    try:
        with open(config_path(name_or_path), encoding="utf-8-sig") as f:
            cfg = yaml.safe_load(f)
    except (OSError, ValueError, yaml.YAMLError):
        return False
    return isinstance(cfg, dict) and cfg.get("kind") == KIND


def resolve_study(cfg: Dict[str, Any]) -> Dict[str, Any]:
    """``cfg`` over :data:`DEFAULTS` (mapping sections one level deep), validated."""
    from ...reference.text import TextConfig
    from .study_evaluator import EVALUATORS

    out = over_defaults(cfg, DEFAULTS, "study config", "kind, name, seeds, ..., variants")
    if out["kind"] != KIND:
        raise AblateConfigError(f"kind={out['kind']!r}: expected {KIND!r}")
    _check("name", out["name"], str)
    for k, lo in (("batch", 1), ("max_frames", 8), ("min_frames", 4), ("diffusion_steps", 1)):
        _check(k, out[k], int, _range(lo))
    _check("lr", out["lr"], float)
    _check("data", out.get("data"), str, optional=True)
    seeds = out["seeds"]
    if not isinstance(seeds, list) or not seeds or len(set(map(str, seeds))) != len(seeds):
        raise AblateConfigError(f"seeds={seeds!r}: expected a non-empty list of distinct ints >= 0")
    for s in seeds:
        _check("seeds[]", s, int, _range(0))
    for section in ("model", "text", "sparse", "snapshots", "eval", "evaluator"):
        _check(section, out[section], dict)
    try:
        TextConfig.from_dict(out["text"])
    except (TypeError, ValueError) as e:
        raise AblateConfigError(f"text: {e}") from None
    _check_keys("snapshots", out["snapshots"], ["steps", "seconds"])
    steps, secs = out["snapshots"].get("steps") or [], out["snapshots"].get("seconds") or []
    if not isinstance(steps, list) or not isinstance(secs, list) or not (steps or secs):
        raise AblateConfigError("snapshots: expected lists steps and/or seconds, at least one entry")
    for s in steps:
        _check("snapshots.steps[]", s, int, _range(1))
    for s in secs:
        _check("snapshots.seconds[]", s, float)
        if s <= 0:
            raise AblateConfigError(f"snapshots.seconds[]={s!r}: expected a float > 0")
    out["snapshots"] = {"steps": sorted(set(steps)), "seconds": sorted(set(float(s) for s in secs))}
    if out["clock"] not in CLOCKS:
        raise AblateConfigError(f"clock={out['clock']!r}: expected one of {sorted(CLOCKS)}")
    _check_keys("eval", out["eval"], list(DEFAULTS["eval"]))
    _check("eval.split", out["eval"]["split"], str)
    _check("eval.limit", out["eval"]["limit"], int, _range(2), optional=True)
    _check("eval.batch", out["eval"]["batch"], int, _range(1))
    kind = out["evaluator"].get("kind")
    if kind not in EVALUATORS:
        raise AblateConfigError(f"evaluator.kind={kind!r}: expected one of {sorted(EVALUATORS)}{closest(str(kind), list(EVALUATORS))}")
    settings_type = EVALUATORS[kind][0]
    try:
        settings_type(**{k: v for k, v in out["evaluator"].items() if k != "kind"})
    except TypeError as e:
        raise AblateConfigError(f"evaluator: {e}") from None
    _check_primary(out)
    variants = out.get("variants")
    if not isinstance(variants, list) or not variants:
        raise AblateConfigError("the config lists no variants")
    check_variants(variants)
    return out


def _check_primary(out: Dict[str, Any]) -> None:
    """``primary``: the pre-registered endpoints (``seconds`` and ``steps``: snapshots of the config;
    ``metrics``: names of :data:`METRICS`), read by :mod:`~smdm_plugin.apps.ablate.paired`."""
    pre = out["primary"]
    _check("primary", pre, dict)
    if not pre:
        return
    _check_keys("primary", pre, ["seconds", "steps", "metrics"])
    for key, have in (("seconds", out["snapshots"]["seconds"]), ("steps", out["snapshots"]["steps"])):
        vals = pre.get(key, [])
        if not isinstance(vals, list) or any(v not in have for v in vals):
            raise AblateConfigError(f"primary.{key}={vals!r}: expected a list of the config's snapshots.{key} {have}")
    metrics = pre.get("metrics")
    if not isinstance(metrics, list) or not metrics or any(m not in METRICS for m in metrics):
        raise AblateConfigError(f"primary.metrics={metrics!r}: expected a non-empty list of {list(METRICS)}")
    if not (pre.get("seconds") or pre.get("steps")):
        raise AblateConfigError("primary: names metrics but no snapshot (seconds and/or steps)")


def _range(lo: float):
    from ...support.values import Range

    return Range(lo)


def load_study(name_or_path: str) -> Dict[str, Any]:
    """The resolved study config of a YAML file or packaged grid name; errors name the file."""
    import yaml

    p = config_path(name_or_path)
    try:
        with open(p, encoding="utf-8-sig") as f:
            cfg = yaml.safe_load(f)
    except (OSError, yaml.YAMLError) as e:
        raise AblateConfigError(f"{p}: cannot read it as YAML ({' '.join(str(e).split())})") from None
    try:
        return resolve_study(cfg if cfg is not None else {})
    except ValueError as e:
        raise type(e)(f"{p}: {e}") from None


# ----------------------------------------------------------------------------------------- clocks
#: how training time is measured: process CPU time (default; robust to other load on a shared
#: machine, torch on one thread) or wall time
CLOCKS: Dict[str, Callable[[], float]] = {"cpu": time.process_time, "wall": time.perf_counter}


# ----------------------------------------------------------------------------------------- data
class StudyData:
    """The train split (captions, for training and the evaluator) and the evaluation split
    (raw features ``[M, N, 263]``, lengths, first captions), with a fingerprint of every file read."""

    def __init__(self, root: str, cfg: Dict[str, Any]) -> None:
        from ...io.humanml3d import load_humanml3d
        from ...training.data import MotionSet

        N, lo = int(cfg["max_frames"]), int(cfg["min_frames"])
        self.root = root
        self.train = MotionSet.from_split(load_humanml3d(root, "train", N, lo, captions=True), captions=True)
        ev_split = load_humanml3d(root, cfg["eval"]["split"], N, lo, captions=True)
        ev = MotionSet.from_split(ev_split, captions=True)
        limit = cfg["eval"]["limit"]
        keep = list(range(len(ev)))[: limit or None]
        x, lengths = ev.padded(keep)
        self.mean, self.std = ev.mean, ev.std
        self.ids = [ev.ids[i] for i in keep]
        self.lengths = lengths  # [M]
        self.norm = x  # [M, N, 263] normalised, zero-padded
        self.raw = x * torch.from_numpy(self.std) + torch.from_numpy(self.mean)
        self.captions = [ev.captions[i][0] for i in keep]  # texts: what the generator is given
        #: the same captions as :class:`~smdm_plugin.metrics.evaluator.vocab.Caption` (text + word/POS tokens)
        self.caption_objs = [ev_split.captions[i][0] for i in keep]
        self.split = cfg["eval"]["split"]
        files = [os.path.join(root, n) for n in ("Mean.npy", "Std.npy", "train.txt", f"{cfg['eval']['split']}.txt")]
        val_ids: List[str] = []
        if os.path.exists(os.path.join(root, "val.txt")):  # an evaluator may select its weights on val
            files.append(os.path.join(root, "val.txt"))
            with open(os.path.join(root, "val.txt")) as f:
                val_ids = [v for v in f.read().split() if os.path.exists(os.path.join(root, "new_joint_vecs", f"{v}.npy"))]
        for i in list(self.train.ids) + self.ids + val_ids:
            files += [os.path.join(root, "new_joint_vecs", f"{i}.npy"), os.path.join(root, "texts", f"{i}.txt")]
        self.fingerprint = fingerprint_files(root, files)


# ----------------------------------------------------------------------------------------- scoring
def score_set(evaluator, raw: torch.Tensor, norm: torch.Tensor, lengths: torch.Tensor, text_emb: np.ndarray,
              real_emb: np.ndarray, mean: np.ndarray, std: np.ndarray) -> Dict[str, float]:
    """Every metric of one set of motions (one per caption, row ``i`` for caption ``i``): FID with its
    bootstrap interval (``fid_low``, ``fid_high``), R-precision and matching score averaged over
    :data:`RETRIEVAL_DRAWS` pools (:data:`SCORING`), diversity, jitter, speed, j/s, foot skating."""
    from ...metrics.feature_measures import per_motion_quality
    from ...metrics.t2m import diversity, fid_bootstrap, retrieval

    emb = evaluator.embed_motion(raw, lengths).double().numpy()
    rs = [retrieval(text_emb, emb, seed=d) for d in range(RETRIEVAL_DRAWS)]
    r = rs[0]
    top = {k: float(np.mean([getattr(x, k) for x in rs])) for k in ("top1", "top2", "top3", "matching_score")}
    fid = fid_bootstrap(emb, real_emb, FID_RESAMPLES, paired=True, seed=0)
    q = per_motion_quality(norm, lengths, mean, std)
    return {"fid": fid.fid, "fid_low": fid.low, "fid_high": fid.high, "r_precision_top1": top["top1"],
            "r_precision_top2": top["top2"], "r_precision_top3": top["top3"], "matching_score": top["matching_score"],
            "diversity": diversity(emb, seed=0)[0],
            "jitter": float(np.nanmean(q["jitter"])), "speed": float(np.nanmean(q["speed"])),
            # the set's j/s as smdm_plugin.metrics.jitter_per_speed reduces it: mean jitter / mean speed
            "jitter_per_speed": float(np.nanmean(q["jitter"]) / max(np.nanmean(q["speed"]), 1e-9)),
            "foot_skating": float(np.nanmean(q["foot_skating"])), "retrieval_pool": r.pool_size,
            "retrieval_scored": r.n_scored}


def generate(model, diffusion, text_cfg, data: StudyData, seed: int, batch: int, device: torch.device) -> torch.Tensor:
    """One motion per caption of the evaluation split, normalised ``[M, N, 263]`` (zero past each
    length): batches of ``batch`` in order of length (each batch as long as its longest motion),
    noise from a generator seeded by ``seed`` alone (the same for every variant)."""
    from ...reference.text import sample_with_text
    from ...training.trainer import mix_seed

    was_training = model.training
    model.eval()
    M, N, D = data.norm.shape
    out = torch.zeros(M, N, D)
    order = sorted(range(M), key=lambda i: int(data.lengths[i]))
    g = torch.Generator(device=device).manual_seed(mix_seed(seed, 7))
    for s in range(0, M, batch):
        idx = order[s:s + batch]
        L = data.lengths[idx]
        n = int(L.max())
        x = sample_with_text(model, diffusion, text_cfg, [data.captions[i] for i in idx], L, n, device, g)
        x = x.squeeze(2).permute(0, 2, 1).cpu()  # [b, n, D]
        x = x * (torch.arange(n)[None, :, None] < L[:, None, None]).to(x.dtype)
        out[idx, :n] = x
    model.train(was_training)
    return out


# ----------------------------------------------------------------------------------------- one run
def run_seed(cfg: Dict[str, Any], variant: Dict[str, Any], seed: int, data: StudyData, evaluator, text_emb: np.ndarray,
             real_emb: np.ndarray, device: torch.device, log: Callable[[str], Any] = print,
             checkpoint_dir: Optional[str] = None) -> Dict[str, Any]:
    """Train ``variant`` with ``seed`` until every snapshot is passed, scoring at each; returns the
    run's record (``snapshots``: one entry per snapshot, with ``kind`` steps|seconds, ``at``,
    ``step``, ``train_s`` (the configured clock), ``train_cpu_s``, ``train_wall_s``, metrics).

    ``checkpoint_dir``: after every snapshot the trainer (weights, optimiser, random streams, step)
    and the run's progress (clocks, snapshots so far) are saved there, and a run that finds them
    continues from the last one (``smdm ablate --resume`` after an interruption: at most the training
    since the last snapshot is redone; the clocks continue from their saved values)."""
    from ...runtime.distributed import DistContext
    from ...reference.text import TextConfig
    from ...training.trainer import TrainConfig, Trainer

    text_cfg = TextConfig.from_dict(cfg["text"])
    sc = sparse_config(cfg, variant)
    progress: Dict[str, Any] = {"step_marks": list(cfg["snapshots"]["steps"]),
                                "time_marks": list(cfg["snapshots"]["seconds"]),
                                "spent": {"cpu": 0.0, "wall": 0.0}, "snapshots": [], "eval_s": 0.0}
    tc = TrainConfig(steps=max(progress["step_marks"] or [1]), batch=int(cfg["batch"]), lr=float(cfg["lr"]),
                     diffusion_steps=int(cfg["diffusion_steps"]), seed=int(seed), model=dict(cfg["model"]),
                     sparse=sc, text=text_cfg)
    trainer = Trainer(tc, data.train, dist=DistContext(device=device))
    if checkpoint_dir is not None:
        restored = _restore(trainer, checkpoint_dir)
        if restored is not None:
            progress = restored
            log(f"    {variant['name']} seed {seed}: continuing from step {trainer.step_count} "
                f"({progress['spent'][cfg['clock']]:.1f} s {cfg['clock']}) in {checkpoint_dir}")
    spent, snaps = progress["spent"], progress["snapshots"]
    step_marks, time_marks = progress["step_marks"], progress["time_marks"]
    while step_marks or time_marks:
        c0, w0 = time.process_time(), time.perf_counter()
        trainer.step()
        spent["cpu"] += time.process_time() - c0
        spent["wall"] += time.perf_counter() - w0
        t_now = spent[cfg["clock"]]
        hits = []
        if step_marks and trainer.step_count >= step_marks[0]:
            hits.append(("steps", step_marks.pop(0)))
        while time_marks and t_now >= time_marks[0]:
            hits.append(("seconds", time_marks.pop(0)))
        if not hits:
            continue
        e0 = time.perf_counter()
        gen = generate(trainer.model, trainer.diffusion, text_cfg, data, seed, int(cfg["eval"]["batch"]), device)
        raw = gen * torch.from_numpy(data.std) + torch.from_numpy(data.mean)
        m = score_set(evaluator, raw, gen, data.lengths, text_emb, real_emb, data.mean, data.std)
        progress["eval_s"] += time.perf_counter() - e0
        recent = trainer.losses[-max(1, min(50, len(trainer.losses) // 10)):]
        for kind, at in hits:
            snaps.append({"kind": kind, "at": at, "step": trainer.step_count, "train_s": t_now,
                          "train_cpu_s": spent["cpu"], "train_wall_s": spent["wall"],
                          "loss": float(np.mean(recent)), **m})
        log(f"    {variant['name']} seed {seed}: {', '.join(f'{a:g} {k}' for k, a in hits)} -> step "
            f"{trainer.step_count}, {t_now:.1f} s {cfg['clock']}, FID {m['fid']:.3f}, R@3 {m['r_precision_top3']:.3f}, "
            f"j/s {m['jitter_per_speed']:.0f}")
        if checkpoint_dir is not None and (step_marks or time_marks):
            _checkpoint(trainer, checkpoint_dir, progress)
    return {"name": variant["name"], "seed": int(seed), "status": Status.OK, "steps": trainer.step_count,
            "steps_per_cpu_s": trainer.step_count / max(spent["cpu"], 1e-9), "train_cpu_s": spent["cpu"],
            "train_wall_s": spent["wall"], "eval_wall_s": progress["eval_s"], "snapshots": snaps,
            "sparse_config": None if sc is None else sc.to_dict(), "losses": trainer.losses}


def _checkpoint_of(folder: str, provenance: Dict[str, Any]) -> None:
    """Make ``folder`` a checkpoint folder of the run of ``provenance``: one left by another run (other
    settings, data, version, seed, device) is deleted, so that run is never continued here."""
    import json

    from ..common.provenance import differences

    path = os.path.join(folder, "provenance.json")
    if os.path.isdir(folder):
        try:
            with open(path, encoding="utf-8") as f:
                stored = json.load(f)
        except (OSError, ValueError):
            stored = None
        if differences(stored, provenance):
            shutil.rmtree(folder)
    os.makedirs(folder, exist_ok=True)
    atomic_write_json(path, provenance)


def _progress_file(step: int) -> str:
    return f"progress{step:09d}.json"


def _checkpoint(trainer, folder: str, progress: Dict[str, Any]) -> None:
    """Save ``progress`` (as ``progress<step>.json``) then the trainer's checkpoint (its
    ``train_state.pt`` written last: its presence says the step is complete) into ``folder``, and
    delete the files of earlier steps."""
    import re

    step = trainer.step_count
    os.makedirs(folder, exist_ok=True)
    atomic_write_json(os.path.join(folder, _progress_file(step)), progress)
    trainer.save(folder)
    keep = {_progress_file(step), trainer.checkpoint_name()}
    for name in os.listdir(folder):
        if re.fullmatch(r"(progress\d{9}\.json|model\d{9}\.pt)", name) and name not in keep:
            os.remove(os.path.join(folder, name))


def _restore(trainer, folder: str) -> Optional[Dict[str, Any]]:
    """The progress saved by :func:`_checkpoint` with ``trainer`` restored to its step, or None (no
    complete checkpoint in ``folder``: the run starts at step 0)."""
    import json

    from ...io.checkpoint_files import read_state_dict
    from ...training.trainer import TRAIN_STATE_FILENAME

    path = os.path.join(folder, TRAIN_STATE_FILENAME)
    if not os.path.exists(path):
        return None
    state = read_state_dict(path, what="training state")
    step = int(state.get("step", -1)) if isinstance(state, dict) else -1
    prog = os.path.join(folder, _progress_file(step))
    if not os.path.exists(prog):
        return None
    with open(prog, encoding="utf-8") as f:
        progress = json.load(f)
    trainer.load_state(state, read_state_dict(os.path.join(folder, f"model{step:09d}.pt")), where=path)
    return progress


# ----------------------------------------------------------------------------------------- aggregation
#: Student-t quantiles t(0.975, df) for df = 1..30 (beyond: 1.96)
_T975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145, 2.131,
         2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042)


def t_interval(values: Sequence[float]) -> Tuple[float, float, int]:
    """``(mean, half-width, n)`` of the 95% Student-t interval over finite ``values``
    (``t(0.975, n-1) * sd / sqrt(n)``, sd with ddof 1); half-width NaN for n < 2."""
    v = np.asarray([x for x in values if x is not None and math.isfinite(x)], np.float64)
    if v.size == 0:
        return float("nan"), float("nan"), 0
    if v.size < 2:
        return float(v.mean()), float("nan"), 1
    t = _T975[v.size - 2] if v.size - 1 <= len(_T975) else 1.96
    return float(v.mean()), float(t * v.std(ddof=1) / math.sqrt(v.size)), int(v.size)


def snapshot_label(kind: str, at: float, clock: str) -> str:
    return f"{int(at)} steps" if kind == "steps" else f"{at:g} s {clock}"


def aggregate(cfg: Dict[str, Any], runs: Dict[str, List[Dict[str, Any]]]) -> List[Dict[str, Any]]:
    """One row per variant × snapshot: per metric (and step / train time) the per-seed values, mean,
    95% t-interval half-width and n."""
    rows = []
    marks = [("steps", a) for a in cfg["snapshots"]["steps"]] + [("seconds", a) for a in cfg["snapshots"]["seconds"]]
    for v in cfg["variants"]:
        recs = [r for r in runs.get(v["name"], []) if is_ok(r)]
        for kind, at in marks:
            snaps = [s for r in recs for s in r["snapshots"] if s["kind"] == kind and s["at"] == at]
            row: Dict[str, Any] = {"variant": v["name"], "kind": kind, "at": at,
                                   "snapshot": snapshot_label(kind, at, cfg["clock"]), "seeds": len(snaps)}
            for k in ("step", "train_s", "loss") + METRICS:
                vals = [float(s[k]) for s in snaps]
                mean, hw, n = t_interval(vals)
                row[k] = {"mean": mean, "ci95": hw, "n": n, "values": vals}
            rows.append(row)
    return rows


# ----------------------------------------------------------------------------------------- report
def _fmt(m: Dict[str, Any], spec: str) -> str:
    if m["n"] == 0 or not math.isfinite(m["mean"]):
        return "—"
    if not math.isfinite(m["ci95"]):
        return format(m["mean"], spec)
    return f"{format(m['mean'], spec)} ± {format(m['ci95'], spec)}"


TABLE_COLUMNS = (("step", ".0f"), ("train_s", ".1f"), ("fid", ".3f"), ("r_precision_top1", ".3f"),
                 ("r_precision_top3", ".3f"), ("matching_score", ".3f"), ("diversity", ".3f"),
                 ("jitter_per_speed", ".0f"), ("speed", ".2f"), ("jitter", ".0f"), ("foot_skating", ".3f"))
HEADERS = {"step": "steps", "train_s": "train s", "fid": "FID ↓", "r_precision_top1": "R@1 ↑",
           "r_precision_top3": "R@3 ↑", "matching_score": "MM-Dist ↓", "diversity": "diversity →",
           "jitter_per_speed": "j/s (1/s²) →", "speed": "speed (m/s)", "jitter": "jitter (m/s³)", "foot_skating": "skating ↓"}


def write_outputs(cfg: Dict[str, Any], out: str, runs: Dict[str, List[Dict[str, Any]]], reference: Dict[str, Any],
                  meta: Dict[str, Any]) -> str:
    """``results.json``, ``results.csv``, ``results.md`` and ``fid_vs_time.png``; returns the markdown."""
    rows = aggregate(cfg, runs)
    clock = cfg["clock"]
    atomic_write_json(os.path.join(out, "results.json"), {
        "config": cfg, "interval": "95% Student-t over seeds: mean ± t(0.975, n-1)·sd/√n (sd ddof 1)",
        "clock": clock, "reference": reference, "rows": rows, **meta,
        "runs": {k: [{kk: vv for kk, vv in r.items() if kk != "losses"} for r in v] for k, v in runs.items()}})
    with atomic_open(os.path.join(out, "results.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["variant", "snapshot", "kind", "at", "metric", "mean", "ci95", "n", "values"])
        for r in rows:
            for k in ("step", "train_s", "loss") + METRICS:
                m = r[k]
                w.writerow([r["variant"], r["snapshot"], r["kind"], r["at"], k, m["mean"], m["ci95"], m["n"],
                            " ".join(f"{x:.6g}" for x in m["values"])])
    head = "| variant | snapshot | " + " | ".join(HEADERS[k] for k, _ in TABLE_COLUMNS) + " |"
    sep = "| --- | --- |" + " ---: |" * len(TABLE_COLUMNS)
    lines = [f"# {cfg['name']}: quality versus training compute", "",
             f"Data {meta.get('data')} (fingerprint {meta.get('data_fingerprint')}): {meta.get('train_motions')} training "
             f"motions, {meta.get('eval_motions')} evaluated ({cfg['eval']['split']} split, first caption each, "
             f"length cut to {cfg['max_frames']} frames). TinyMDM {cfg['model']}, {cfg['diffusion_steps']} diffusion steps, "
             f"batch {cfg['batch']}, lr {cfg['lr']}, text {cfg['text']}; seeds {cfg['seeds']}. Training time: "
             f"{'process CPU time of the training steps (1 thread)' if clock == 'cpu' else 'wall time of the training steps'}"
             ", evaluation excluded. Values: mean ± 95% Student-t half-width over seeds.", "",
             f"Evaluator: {meta.get('evaluator')}.", ""]
    by_kind = {"steps": "Equal optimiser steps", "seconds": f"Equal training time ({clock} seconds)"}
    for kind in ("steps", "seconds"):
        sel = [r for r in rows if r["kind"] == kind]
        if not sel:
            continue
        lines += [f"## {by_kind[kind]}", "", head, sep]
        for at in sorted({r["at"] for r in sel}):
            for r in sel:
                if r["at"] == at:
                    lines.append(f"| {r['variant']} | {r['snapshot']} | "
                                 + " | ".join(_fmt(r[k], spec) for k, spec in TABLE_COLUMNS) + " |")
        lines.append("")
    ref = reference
    lines += ["## Real motion (reference)", "",
              f"Real {cfg['eval']['split']} motions scored as the generated ones: R@1 {ref['r_precision_top1']:.3f}, "
              f"R@3 {ref['r_precision_top3']:.3f}, MM-Dist {ref['matching_score']:.3f}, diversity {ref['diversity']:.3f}, "
              f"j/s {ref['jitter_per_speed']:.0f} 1/s² at speed {ref['speed']:.2f} m/s, jitter {ref['jitter']:.0f} m/s³, skating {ref['foot_skating']:.3f}; "
              f"FID of the real train motions against them: {ref['fid_train_vs_eval']:.3f} (FID of the set against "
              f"itself is 0). Retrieval pool {ref['retrieval_pool']} ({ref['retrieval_scored']} motions scored, "
              f"{RETRIEVAL_DRAWS} draws; chance R@1 {1 / ref['retrieval_pool']:.3f}).", "",
              "What a FID here is read against (95% bootstrap intervals over the motions):", "",
              *reference_lines({"reference": ref})]
    failed = [(n, r) for n, rs in runs.items() for r in rs if status_of(r) is Status.FAILED]
    for n, r in failed:
        lines.append(f"{n} seed {r.get('seed')} failed: {r.get('error')}")
    lines.append("Plot: fid_vs_time.png (FID against training time, mean ± 95% interval over seeds).")
    text = "\n".join(lines)
    atomic_write_text(os.path.join(out, "results.md"), text + "\n")
    plot_fid_vs_time(cfg, rows, reference, os.path.join(out, "fid_vs_time.png"))
    return text


def plot_fid_vs_time(cfg: Dict[str, Any], rows: List[Dict[str, Any]], reference: Dict[str, Any], path: str) -> None:
    """FID against training time: each variant's time snapshots (mean over seeds, 95% bars), dense
    and sparse on one plot; the equal-step snapshots as hollow markers at their mean time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 5))
    for k, v in enumerate(cfg["variants"]):
        color = f"C{k}"
        pts = sorted(((r["train_s"]["mean"], r["fid"]["mean"], r["fid"]["ci95"]) for r in rows
                      if r["variant"] == v["name"] and r["kind"] == "seconds" and r["fid"]["n"]), key=lambda p: p[0])
        if pts:
            x, y, e = map(np.asarray, zip(*pts))
            ax.errorbar(x, y, yerr=np.nan_to_num(e), color=color, marker="o", capsize=3,
                        lw=2 if v.get("dense") or v["name"].startswith("sparse (VW)") else 1, label=v["name"])
        st = [(r["train_s"]["mean"], r["fid"]["mean"]) for r in rows
              if r["variant"] == v["name"] and r["kind"] == "steps" and r["fid"]["n"]]
        if st:
            ax.scatter(*zip(*st), facecolors="none", edgecolors=color, marker="s", s=50)
    ax.axhline(reference["fid_train_vs_eval"], color="gray", ls="--", lw=1, label="real train vs eval motions")
    for key, ls, label in (("fid_train_matched", "-.", "real train, eval captions and lengths"),
                           ("fid_floor", ":", "floor: eval vs a second draw of itself")):
        if key in reference:  # the anchors (results written before 0.8 have only the first line)
            ax.axhline(reference[key], color="black", ls=ls, lw=1, label=label)
    ax.set_xlabel(f"training time ({'process CPU' if cfg['clock'] == 'cpu' else 'wall'} seconds, evaluation excluded)")
    ax.set_ylabel("FID (study evaluator) ↓")
    ax.set_title(f"{cfg['name']}: FID vs training time (squares: equal-step snapshots {cfg['snapshots']['steps']})",
                 fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------------------- the study
def build_evaluator(cfg: Dict[str, Any], data: StudyData, out: str, log: Callable[[str], Any]):
    """The evaluator of ``cfg['evaluator']``, trained on the train split once and cached in
    ``out/evaluator/<key>/`` (key: data fingerprint + settings + package version)."""
    from ... import __version__
    from .study_evaluator import EVALUATORS, cached_evaluator

    kind = cfg["evaluator"]["kind"]
    settings_type, train, load = EVALUATORS[kind]
    settings = settings_type(**{k: v for k, v in cfg["evaluator"].items() if k != "kind"})
    key = stable_hash({"kind": kind, "settings": cfg["evaluator"], "data": data.fingerprint,
                       "max_frames": cfg["max_frames"], "min_frames": cfg["min_frames"], "version": __version__})
    folder = os.path.join(out, "evaluator", f"{kind}-{key}")

    def build():
        log(f"  training the {kind} evaluator on the train split (cached in {folder})")
        return train(data, settings, log)

    return cached_evaluator(folder, build, load), key, folder


@dataclass(frozen=True)
class StudyRun:
    """One (variant, seed) of the study: its folder, the settings and provenance of a run now, what
    the folder holds and whether this invocation runs it (``run``)."""

    variant: Dict[str, Any]
    seed: int
    vdir: str
    settings: Dict[str, Any]
    provenance: Dict[str, Any]
    cached: Cached
    run: bool


@dataclass(frozen=True)
class Reference:
    """The evaluator and what every run is scored against: caption and real-motion embeddings
    (``[M, d]`` float64 numpy), the real motions' own scores (``fid_train_vs_eval`` included)."""

    evaluator: Any
    key: str
    text_emb: np.ndarray
    real_emb: np.ndarray
    scores: Dict[str, Any]


def run_study(cfg: Dict[str, Any], out: str, data_root: str, device: str = "cpu", only: Optional[Sequence[str]] = None,
              seeds: Optional[Sequence[int]] = None, resume: bool = False, overwrite: bool = False,
              log: Callable[[str], Any] = print, report_only: bool = False) -> Dict[str, List[Record]]:
    """Run the study ``cfg`` into ``out`` (see the module docstring); returns ``{variant: [run per seed]}``.
    ``report_only`` (with ``resume``): train nothing, rebuild the report from the current results
    (e.g. while other processes, each with its own ``--only``/``--seeds``, still run)."""
    if resume and overwrite:
        raise ValueError("run_study: resume and overwrite exclude each other")
    selected = select_variants(cfg, only)
    run_seeds = [int(s) for s in (seeds if seeds is not None else cfg["seeds"])]
    unknown = [s for s in run_seeds if s not in cfg["seeds"]]
    if unknown:
        raise ValueError(f"--seeds {unknown}: not among the config's seeds {cfg['seeds']}")
    check_out_dir(out, resume, overwrite)
    dev = resolve_device(device)
    data = StudyData(data_root, cfg)
    log(f"study {cfg['name']}: {len(data.train)} training / {len(data.ids)} evaluation motions from {data_root} "
        f"(fingerprint {data.fingerprint}); snapshots at {cfg['snapshots']['steps']} steps and "
        f"{cfg['snapshots']['seconds']} s ({cfg['clock']}); seeds {run_seeds}; device {dev}")
    _write_study_files(cfg, out, data, data_root, dev)
    ref = _reference(cfg, data, out, log)
    meta = _meta(cfg, data, data_root, ref, dev)
    plan = _plan(cfg, out, data, ref.key, dev, selected, run_seeds, report_only, overwrite)
    runs: Dict[str, List[Record]] = {v["name"]: [] for v in cfg["variants"]}
    try:
        for item in plan:
            if item.run and overwrite:  # run again from step 0, not from a checkpoint
                shutil.rmtree(os.path.join(item.vdir, CHECKPOINT_DIR), ignore_errors=True)
            rec = _run_one(cfg, item, data, ref, dev, log) if item.run else (
                {**item.cached.record, "reused": True} if item.cached.state is CacheState.CURRENT else None)
            if rec is not None:
                runs[item.variant["name"]].append(rec)
    finally:  # the report is written even when interrupted: it shows what is done
        write_outputs(cfg, out, runs, ref.scores, meta)
    return runs


def _write_study_files(cfg: Dict[str, Any], out: str, data: StudyData, data_root: str, dev: torch.device) -> None:
    """``out/`` with its manifest (what the folder is, last run) and ``config.yaml`` (the config as run)."""
    import yaml

    from ... import __version__

    os.makedirs(out, exist_ok=True)
    atomic_write_json(os.path.join(out, MANIFEST), {
        "tool": "smdm ablate", "kind": KIND, "format": 1, "grid": cfg["name"],
        "variants": [v["name"] for v in cfg["variants"]], "seeds": cfg["seeds"], "package_version": __version__,
        "data_root": os.path.abspath(data_root), "data_fingerprint": data.fingerprint, "device": dev.type,
        "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
    atomic_write_text(os.path.join(out, "config.yaml"), yaml.safe_dump(cfg, sort_keys=False))


def _reference(cfg: Dict[str, Any], data: StudyData, out: str, log: Callable[[str], Any]) -> Reference:
    """The (cached) evaluator, the embeddings of the captions and real motions, and the real motions'
    scores with the FID anchors of :func:`fid_anchors`."""
    evaluator, key, _ = build_evaluator(cfg, data, out, log)
    text_emb = evaluator.embed_text(data.caption_objs).double().numpy()
    real_emb = evaluator.embed_motion(data.raw, data.lengths).double().numpy()
    scores = score_set(evaluator, data.raw, data.norm, data.lengths, text_emb, real_emb, data.mean, data.std)
    scores.update(fid_anchors(evaluator, data, real_emb, cfg["text"]))
    return Reference(evaluator, key, text_emb, real_emb, scores)


def matched_train(data: StudyData, text: Dict[str, Any]) -> Tuple[List[int], torch.Tensor]:
    """For each evaluation motion ``i`` (caption ``i``, length ``L_i``) the train motion a generator
    that only memorised its training set would give: the one whose caption is nearest (cosine of the
    study's own text encoder, any of its captions) among those at least ``L_i`` frames long (all when
    none is), cut to its first ``L_i`` frames. Returns ``(train indices [M], lengths [M])``."""
    from ...reference.text import TextConfig

    enc = TextConfig.from_dict(text).build()
    ev = enc.encode(data.captions)                                       # [M, dim], unit rows
    owner = [i for i, caps in enumerate(data.train.captions) for _ in caps]
    tr = enc.encode([c for caps in data.train.captions for c in caps])   # [C, dim]
    _, train_L = data.train.padded()
    sim = ev @ tr.T                                                      # [M, C]
    idx, lens = [], []
    for i, L in enumerate(data.lengths.tolist()):
        ok = np.array([int(train_L[o]) >= L for o in owner])
        c = int(np.argmax(np.where(ok, sim[i], -np.inf))) if ok.any() else int(np.argmax(sim[i]))
        idx.append(owner[c])
        lens.append(min(int(L), int(train_L[owner[c]])))
    return idx, torch.tensor(lens)


def fid_anchors(evaluator, data: StudyData, real_emb: np.ndarray, text: Dict[str, Any]) -> Dict[str, Any]:
    """What a FID of ``M`` generated motions against the ``M`` real evaluation motions is read against
    (each with a 95% bootstrap interval, :func:`~smdm_plugin.metrics.t2m.fid_bootstrap`):

    * ``fid_floor`` — the real motions against a second draw of themselves (two independent resamples
      of the ``M``; mean and percentiles of :data:`FID_RESAMPLES` pairs): a perfect generator's FID;
    * ``fid_train_matched`` — the real train motions with the evaluation captions and lengths
      (:func:`matched_train`): a generator that reproduces its training motions;
    * ``fid_train_vs_eval`` — every real train motion (first ``max_frames``) against them;
    * ``fid_train_sample`` — ``M`` train motions drawn without replacement (mean and percentiles over
      :data:`FID_RESAMPLES` draws): the last at the generated sets' size."""
    from ...metrics.t2m import fid_bootstrap, frechet_distance

    std, mean = torch.from_numpy(data.std), torch.from_numpy(data.mean)
    train_x, train_L = data.train.padded()
    train_emb = evaluator.embed_motion(train_x * std + mean, train_L).double().numpy()
    idx, lens = matched_train(data, text)
    matched_emb = evaluator.embed_motion(train_x[idx] * std + mean, lens).double().numpy()
    floor = fid_bootstrap(real_emb, real_emb, FID_RESAMPLES, seed=1)
    allt = fid_bootstrap(train_emb, real_emb, FID_RESAMPLES, seed=2)
    match = fid_bootstrap(matched_emb, real_emb, FID_RESAMPLES, paired=True, seed=3)
    rng = np.random.default_rng(4)
    M = len(real_emb)
    sample = [frechet_distance(train_emb[rng.choice(len(train_emb), M, replace=False)], real_emb)
              for _ in range(FID_RESAMPLES)] if len(train_emb) >= M else [float("nan")]
    return {"fid_floor": floor.boot_mean, "fid_floor_interval": [floor.boot_low, floor.boot_high],
            "fid_train_matched": match.fid, "fid_train_matched_interval": [match.low, match.high],
            "fid_train_vs_eval": allt.fid, "fid_train_vs_eval_interval": [allt.low, allt.high],
            "fid_train_sample": float(np.mean(sample)),
            "fid_train_sample_interval": [float(np.percentile(sample, 2.5)), float(np.percentile(sample, 97.5))],
            "train_matched": [data.train.ids[i] for i in idx]}


def _meta(cfg: Dict[str, Any], data: StudyData, data_root: str, ref: Reference, dev: torch.device) -> Dict[str, Any]:
    """What the report says about the run (data, evaluator, device, version, threads)."""
    from ... import __version__

    return {"data": data_root, "data_fingerprint": data.fingerprint, "train_motions": len(data.train),
            "eval_motions": len(data.ids), "evaluator_key": ref.key,
            "evaluator": f"{cfg['evaluator']['kind']} {getattr(ref.evaluator, 'report', {})}", "device": dev.type,
            "package_version": __version__, "torch_threads": torch.get_num_threads()}


def _plan(cfg: Dict[str, Any], out: str, data: StudyData, ev_key: str, dev: torch.device, selected: Sequence[str],
          run_seeds: Sequence[int], report_only: bool, overwrite: bool) -> List[StudyRun]:
    """Every (variant, seed) of the config, in order, with what this invocation does with it; a stale
    result that would be replaced without ``overwrite`` stops the study before anything trains."""
    plan, conflicts = [], []
    for v in cfg["variants"]:
        for s in cfg["seeds"]:
            vdir = os.path.join(out, slug(v["name"]), f"seed{s}")
            settings = {**{k: cfg[k] for k in RUN_SETTINGS}, "variant": v, "evaluator_key": ev_key, "scoring": SCORING}
            try:
                sc = sparse_config(cfg, v)
                settings["sparse_config"] = None if sc is None else sc.to_dict()
            except (TypeError, ValueError) as e:
                settings["sparse_config"] = f"invalid: {e}"
            prov = make_provenance(settings, data.fingerprint, max(cfg["snapshots"]["steps"] or [0]), s, dev.type,
                                   clock=cfg["clock"])
            cached = read_cached(vdir, prov)
            run_it = (not report_only and v["name"] in selected and s in run_seeds
                      and (overwrite or cached.state is not CacheState.CURRENT))
            if run_it and cached.state is CacheState.STALE and not overwrite:
                conflicts.append(f"{v['name']!r} seed {s} ({cached.reason})")
            plan.append(StudyRun(v, s, vdir, settings, prov, cached, run_it))
    if conflicts:
        raise OutputExistsError(f"--out {out!r} holds {len(conflicts)} result(s) from another run: "
                                f"{'; '.join(conflicts)}. Pass --overwrite to run them again, or pick another --out")
    return plan


def _run_one(cfg: Dict[str, Any], item: StudyRun, data: StudyData, ref: Reference, dev: torch.device,
             log: Callable[[str], Any]) -> Record:
    """Train and score one (variant, seed), record it atomically (``result.json``, or ``failed.json``
    when it raises: the other runs go on) and return the record."""
    name, s, vdir = item.variant["name"], item.seed, item.vdir
    res_path, fail_path = os.path.join(vdir, RESULT_FILE), os.path.join(vdir, FAILED_FILE)
    os.makedirs(vdir, exist_ok=True)
    atomic_write_json(os.path.join(vdir, "config.json"), item.settings)
    log(f"  {name} seed {s}: training")
    t0 = time.perf_counter()
    ckpt = os.path.join(vdir, CHECKPOINT_DIR)
    _checkpoint_of(ckpt, item.provenance)
    try:
        rec = run_seed(cfg, item.variant, s, data, ref.evaluator, ref.text_emb, ref.real_emb, dev, log,
                       checkpoint_dir=ckpt)
    except Exception as e:  # recorded; the other runs go on
        rec = failure_record(name, e, item.provenance, seed=s)
        atomic_write_json(fail_path, rec)
        if os.path.exists(res_path):
            os.remove(res_path)
        log(f"  {name} seed {s}: FAILED ({rec['error']})")
        return rec
    rec["wall_s"] = time.perf_counter() - t0
    rec["provenance"] = item.provenance
    atomic_write_json(res_path, rec, indent=None)
    if os.path.exists(fail_path):
        os.remove(fail_path)
    shutil.rmtree(ckpt, ignore_errors=True)  # the result is written: the checkpoint has served
    return rec


# ----------------------------------------------------------------------------------------- CLI
def wants_study(argv: Optional[Sequence[str]]) -> bool:
    """Whether ``smdm ablate`` arguments ask for the study (``--quick``, or a ``--config`` of kind
    ``quality_compute``)."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--config", default=None, help="the grid (only read to tell a study from an ablation grid)")
    p.add_argument("--quick", action="store_true", help="the study's quick variant")
    a, _ = p.parse_known_args(list(sys.argv[1:] if argv is None else argv))
    return a.quick or (a.config is not None and is_study_config(a.config))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="smdm ablate", description="The quality-versus-compute study (a config with kind: quality_compute).",
        epilog="Exit status: 0 every run ok, 1 a run failed, 2 bad arguments or a refused --out, 130 interrupted.")
    p.add_argument("--config", default=KIND, help=f"the study config: a YAML path or packaged name (default {KIND})")
    p.add_argument("--quick", action="store_true", help="run the config's quick variant (<config>_quick: seconds)")
    p.add_argument("--out", default=os.path.join("results", KIND), type=output_path(),
                   help=f"results folder (default results/{KIND})")
    p.add_argument("--data", type=existing_path("dir"), default=None,
                   help=f"HumanML3D-format folder with texts/ (default: config 'data' or {DEFAULT_DATA})")
    p.add_argument("--only", nargs="+", default=None, metavar="VARIANT", help="run only these variants")
    p.add_argument("--seeds", nargs="+", type=int, default=None, help="run only these seeds of the config")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--resume", action="store_true", help="reuse (variant, seed) results with the same provenance")
    add_overwrite(g)
    p.add_argument("--report-only", action="store_true",
                   help="with --resume: train nothing, rebuild the report from the finished runs in --out")
    add_common_flags(p, device="cpu", threads_default=1)  # 1 thread: the CPU-time clock measures one core's work
    return p


def _parse(p: argparse.ArgumentParser, argv: Optional[List[str]], grid_options: Sequence[str] = ()
           ) -> argparse.Namespace:
    """``p.parse_args(argv)``, an ablation grid's option (``grid_options``) named as such (not
    "unrecognized": ``smdm ablate --help`` lists it)."""
    a, extra = p.parse_known_args(argv)
    grid = set(grid_options)
    for token in extra:
        option = token.split("=", 1)[0]
        if option.startswith("--") and option in grid:
            p.error(f"argument {option}: an ablation grid's option; the quality-versus-compute study (--config "
                    f"{a.config}{' --quick' if a.quick else ''}) sets it in its config")
    if extra:
        p.error(f"unrecognized arguments: {' '.join(extra)}")
    return a


def main(argv: Optional[List[str]] = None, grid_options: Sequence[str] = ()) -> int:
    """The study's command (``smdm ablate`` hands over when :func:`wants_study`); ``grid_options``: the
    option strings of an ablation grid's parser, named when given here."""
    p = build_parser()
    a = _parse(p, argv, grid_options)
    if a.report_only and not a.resume:
        p.error("argument --report-only: needs --resume (an existing results folder)")
    name = a.config
    if a.quick and not name.endswith("_quick") and not is_study_config(name) and os.path.exists(config_path(name)):
        p.error(f"argument --quick: runs a study config's quick variant; --config {name!r} is an ablation grid "
                "(drop --quick)")
    if a.quick and not name.endswith("_quick"):
        base = name[:-5] if name.endswith(".yaml") else name
        name = base + "_quick" + (".yaml" if name.endswith(".yaml") else "")
    try:
        if not is_study_config(name):
            p.error(f"argument --config: {name!r} is not a study config (kind: {KIND})"
                    if os.path.exists(config_path(name)) else f"argument --config: {name!r} not found")
        cfg = load_study(name)
    except (FileNotFoundError, ValueError) as e:
        p.error(str(e))
    torch.set_num_threads(a.threads)
    data_root = a.data or cfg.get("data") or DEFAULT_DATA
    cfg["data"] = data_root
    try:
        runs = run_study(cfg, a.out, data_root, a.device, a.only, a.seeds, a.resume, a.overwrite,
                         log=print if progress_of(a) else _silent, report_only=a.report_only)
    except (OutputExistsError, FileNotFoundError, ValueError, PermissionError, NotADirectoryError) as e:
        print(f"smdm ablate: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\nsmdm ablate: interrupted; finished runs are kept in {a.out}; rerun with --resume.", file=sys.stderr)
        return 130
    with open(os.path.join(a.out, "results.md"), encoding="utf-8") as f:
        print("\n" + f.read())
    note_printer(a)(f"results: {os.path.abspath(a.out)}")
    return 0 if all(is_ok(r) for rs in runs.values() for r in rs) else 1


def _silent(*_: Any, **__: Any) -> None:
    """The study's log under --no-progress / --quiet: nothing."""
