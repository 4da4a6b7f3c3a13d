"""``smdm ablate``: A/B ablations of sparse keyframe mode on real motion, one results folder.

Every variant of a YAML grid (``smdm_plugin/configs/ablations/table1.yaml``: the paper's Table 1 set) trains the
in-package backbone (:class:`~smdm_plugin.backbone.TinyMDM` + :class:`~smdm_plugin.diffusion.SimpleDiffusion`)
with the *same* seed, initial weights, data order, diffusion steps ``t`` and step count, on
HumanML3D-format motion (``--data``, default ``../shared/data/cmu-humanml3d``: ``new_joint_vecs``,
``new_joints``, ``Mean.npy``/``Std.npy``, ``train.txt``/``val.txt``). Unconditional (no CLIP).

Per variant: final and best training loss, steps/s, wall time, the keyframe reconstruction error
(mean joint position error in mm of linearly interpolating the 22 joints of the validation motions
from the keyframes the variant's selector picks; "—" for dense), and the End-Effector Speed (EES,
cm/frame, :func:`smdm_plugin.metrics.end_effector_speed`) of motions sampled from the trained
model next to the EES of the real validation motions.

Output (``--out``): ``results.md``, ``results.csv``, ``loss_curves.png``, ``config.yaml`` (the grid
as run, with ``--steps``/``--data`` overrides) and per variant ``<slug>/result.json`` +
``<slug>/config.json`` (the resolved settings). Resumable: a variant whose ``result.json`` exists is
not run again; a variant that raises is written to ``<slug>/failed.json`` (traceback) and retried
next time; the others go on.

YAML schema::

    name: table1
    seed: 0
    steps: 300            # optimiser steps per variant
    batch: 16
    max_frames: 196
    diffusion_steps: 100
    lr: 0.0002
    model: {latent_dim: 128, num_layers: 4, num_heads: 4, ff_size: 256, arch: trans_enc, dropout: 0.1}
    sparse: {reduction: 0.8}      # SparseConfig fields shared by the sparse variants
    eval: {samples: 8, frames: 120}
    variants:
      - {name: dense, dense: true}
      - {name: sparse (VW)}
      - {name: random keyframes, sparse: {selector: random}}
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import re
import sys
import time
import traceback
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
import torch

DEFAULT_DATA = os.path.join("..", "shared", "data", "cmu-humanml3d")
DEFAULTS: Dict[str, Any] = {
    "name": "ablation", "seed": 0, "steps": 200, "batch": 16, "max_frames": 196, "diffusion_steps": 100,
    "lr": 2e-4, "log_every": 1,
    "model": {"latent_dim": 128, "num_layers": 4, "num_heads": 4, "ff_size": 256, "arch": "trans_enc",
              "dropout": 0.1},
    "sparse": {"reduction": 0.8},
    "eval": {"samples": 8, "frames": 120, "keyframe_motions": None},
}


# ----------------------------------------------------------------------------------------- config
ABLATIONS_DIR = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "configs", "ablations")


def config_path(name_or_path: str) -> str:
    """A grid's YAML file: a path, or the name of a packaged grid (``table1``, ``defaults``,
    ``quick``: ``smdm_plugin/configs/ablations/<name>.yaml``)."""
    if os.path.exists(name_or_path):
        return name_or_path
    packaged = os.path.join(ABLATIONS_DIR, os.path.basename(name_or_path))
    for cand in (packaged, packaged + ".yaml"):
        if os.path.isfile(cand):
            return cand
    raise FileNotFoundError(f"ablate: --config {name_or_path!r} is neither a file nor a packaged grid "
                            f"({', '.join(sorted(f[:-5] for f in os.listdir(ABLATIONS_DIR)))})")


def load_config(path: str) -> Dict[str, Any]:
    import yaml

    with open(config_path(path)) as f:
        cfg = yaml.safe_load(f) or {}
    return resolve(cfg)


def resolve(cfg: Dict[str, Any]) -> Dict[str, Any]:
    out = json.loads(json.dumps(DEFAULTS))
    for k, v in cfg.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k].update(v)
        else:
            out[k] = v
    variants = out.get("variants") or []
    if not variants:
        raise ValueError("ablate: the config lists no variants")
    names = [v.get("name") for v in variants]
    if any(not n for n in names) or len(set(names)) != len(names):
        raise ValueError(f"ablate: every variant needs a unique name, got {names}")
    return out


def slug(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-") or "variant"


def sparse_config(cfg: Dict[str, Any], variant: Dict[str, Any]):
    from ..core.config import SparseConfig

    if variant.get("dense"):
        return None
    d = dict(cfg.get("sparse") or {})
    d.update(variant.get("sparse") or {})
    return SparseConfig.from_dict(d)


# ----------------------------------------------------------------------------------------- data
class MotionData:
    """HumanML3D-format motions: normalised ``[M, max_frames, 263]`` + lengths, joints for eval."""

    def __init__(self, root: str, max_frames: int = 196, min_frames: int = 40) -> None:
        root_p = Path(root)
        if not (root_p / "Mean.npy").exists():
            raise FileNotFoundError(f"ablate: no HumanML3D-format data at {root} (need Mean.npy, Std.npy, "
                                    "new_joint_vecs/, train.txt); pass --data")
        self.root = root_p
        self.mean = np.load(root_p / "Mean.npy").astype(np.float32)
        self.std = np.load(root_p / "Std.npy").astype(np.float32)
        self.max_frames = max_frames
        self.train = self._load("train", min_frames)
        self.val = self._load("val" if (root_p / "val.txt").exists() else "test", min_frames)

    def _load(self, split: str, min_frames: int) -> Dict[str, Any]:
        ids = [i for i in (self.root / f"{split}.txt").read_text().split() if i]
        x, lengths, joints, kept = [], [], [], []
        for i in ids:
            f = self.root / "new_joint_vecs" / f"{i}.npy"
            if not f.exists():
                continue
            m = np.load(f).astype(np.float32)
            if len(m) < min_frames:
                continue
            L = min(len(m), self.max_frames)
            pad = np.zeros((self.max_frames, m.shape[1]), np.float32)
            pad[:L] = (m[:L] - self.mean) / self.std
            x.append(pad)
            lengths.append(L)
            jf = self.root / "new_joints" / f"{i}.npy"
            joints.append(np.load(jf)[:L].astype(np.float32) if jf.exists() else None)
            kept.append(i)
        if not x:
            raise ValueError(f"ablate: split {split!r} of {self.root} has no usable motion")
        return {"ids": kept, "x": torch.from_numpy(np.stack(x)), "lengths": torch.tensor(lengths),
                "joints": joints}


def batches(n: int, batch: int, steps: int, seed: int) -> List[torch.Tensor]:
    """The index batches of every step (epoch-wise permutations): identical for every variant."""
    g = torch.Generator().manual_seed(seed)
    out: List[torch.Tensor] = []
    perm = torch.randperm(n, generator=g)
    pos = 0
    while len(out) < steps:
        if pos + batch > n:
            perm, pos = torch.randperm(n, generator=g), 0
        out.append(perm[pos:pos + min(batch, n)])
        pos += min(batch, n)
    return out


# ----------------------------------------------------------------------------------------- metrics
def keyframe_error_mm(data: MotionData, sc, limit: Optional[int] = None, seed: int = 0) -> Optional[float]:
    """MPJPE (mm) of interpolating the validation joints from the variant's training keyframes
    (selector on the HumanML3D features, no mask noise)."""
    if sc is None:
        return None
    from ..core.interpolation import interpolate_keyframes
    from ..core.schedule import MaskSchedule

    sched = MaskSchedule(sc.replace(mask_noise=0.0), data.mean, data.std)
    val = data.val
    n = len(val["ids"]) if limit is None else min(limit, len(val["ids"]))
    errs = []
    g = torch.Generator().manual_seed(seed)
    for b in range(n):
        j = val["joints"][b]
        if j is None:
            continue
        L = int(val["lengths"][b])
        x = val["x"][b:b + 1, :L]
        from ..core.selection import select_keyframes

        mask = select_keyframes(sched.features(x), torch.tensor([L]), sc.reduction, sc.selector, generator=g)
        rec = interpolate_keyframes(torch.from_numpy(j).reshape(1, L, -1).double(), mask).reshape(L, -1, 3)
        errs.append(float((rec.numpy() - j).__pow__(2).sum(-1).__pow__(0.5).mean() * 1000.0))
    return float(np.mean(errs)) if errs else None


def _ees(motion_norm: torch.Tensor, lengths: torch.Tensor, data: MotionData) -> Optional[float]:
    try:
        from ..metrics import end_effector_speed
    except ImportError:
        return None
    return float(end_effector_speed(motion_norm, lengths, mean=data.mean, std=data.std))


def validation_loss(model, diffusion, data: "MotionData", device: torch.device, seed: int, n_t: int = 5) -> float:
    """Denoising MSE on the validation motions over all valid frames, at ``n_t`` fixed timesteps
    spread over ``[0, T)`` with fixed noise (identical for every variant). The model runs as it
    would at sampling time (its own keyframe schedule on ``x_t``), so sparse and dense compare on
    the same dense frames. Not comparable with training losses, which sample t at random."""
    from ..reference.diffusion import masked_mse

    val = data.val
    x = val["x"].permute(0, 2, 1).unsqueeze(2).to(device)
    B, N = x.shape[0], x.shape[-1]
    y = {"mask": (torch.arange(N) < val["lengths"][:, None]).view(B, 1, 1, N).to(device),
         "lengths": val["lengths"].to(device)}
    g = torch.Generator().manual_seed(seed + 4)
    out = []
    with torch.no_grad():
        for t in torch.linspace(0, diffusion.num_timesteps - 1, n_t).round().long():
            tt = t.expand(B).to(device)
            noise = torch.randn(x.shape, generator=g).to(device)
            pred = model(diffusion.q_sample(x, tt, noise), tt, {"y": dict(y)})
            out.append(float(masked_mse(pred, x, y["mask"]).mean()))
    return float(np.mean(out))


# ----------------------------------------------------------------------------------------- run
def run_variant(cfg: Dict[str, Any], variant: Dict[str, Any], data: MotionData, device: torch.device,
                progress: bool = False) -> Dict[str, Any]:
    from ..adapters.mdm import sparsify
    from ..reference.backbone import TinyMDM
    from ..reference.diffusion import SimpleDiffusion

    seed = int(cfg["seed"])
    sc = sparse_config(cfg, variant)
    torch.manual_seed(seed)
    model = TinyMDM(njoints=263, nfeats=1, cond_mode="no_cond", **cfg["model"]).to(device)
    diffusion = SimpleDiffusion(int(cfg["diffusion_steps"]))
    if sc is not None:
        sparsify(model, sc, diffusion=diffusion, mean=data.mean, std=data.std)
    opt = torch.optim.AdamW(model.parameters(), lr=float(cfg["lr"]))
    tr = data.train
    steps = int(cfg["steps"])
    order = batches(len(tr["ids"]), int(cfg["batch"]), steps, seed)
    g_t = torch.Generator().manual_seed(seed + 1)
    N = tr["x"].shape[1]
    losses: List[float] = []
    it = range(steps)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc=variant["name"], leave=False)
    model.train()
    torch.manual_seed(seed + 2)  # dropout / mask noise streams start equal
    t0 = time.perf_counter()
    for s in it:
        idx = order[s]
        x = tr["x"][idx].permute(0, 2, 1).unsqueeze(2).to(device)  # [B, 263, 1, N]
        L = tr["lengths"][idx]
        y = {"mask": (torch.arange(N) < L[:, None]).view(-1, 1, 1, N).to(device), "lengths": L.to(device)}
        t = torch.randint(0, diffusion.num_timesteps, (len(idx),), generator=g_t).to(device)
        loss = diffusion.training_losses(model, x, t, {"y": y})["loss"].mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        v = loss.item()
        if not math.isfinite(v):
            raise FloatingPointError(f"loss became {v} at step {s}")
        losses.append(v)
    train_s = time.perf_counter() - t0

    # evaluation: sample unconditionally (the variant's own sampling schedule), EES
    ev = cfg["eval"]
    ns, nf = int(ev.get("samples", 8)), min(int(ev.get("frames", 120)), N)
    model.eval()
    val_loss = validation_loss(model, diffusion, data, device, seed)
    g = torch.Generator().manual_seed(seed + 3)
    lengths = torch.full((ns,), nf, dtype=torch.long)
    y = {"mask": torch.ones(ns, 1, 1, nf, dtype=torch.bool, device=device), "lengths": lengths.to(device)}
    t1 = time.perf_counter()
    sample = diffusion.p_sample_loop(model, (ns, 263, 1, nf), {"y": y}, device=device, generator=g)
    sample_s = time.perf_counter() - t1
    motion = sample.squeeze(2).permute(0, 2, 1).cpu()  # [B, N, 263] normalised
    k = max(1, len(losses) // 10)
    smooth = np.convolve(losses, np.ones(k) / k, mode="valid") if losses else np.array([np.nan])
    return {
        "name": variant["name"], "status": "ok", "steps": steps,
        "final_loss": float(np.mean(losses[-k:])), "best_loss": float(np.min(smooth)), "val_loss": val_loss,
        "steps_per_s": steps / train_s, "train_s": train_s, "sample_s": sample_s,
        "keyframe_error_mm": keyframe_error_mm(data, sc, ev.get("keyframe_motions"), seed),
        "ees": _ees(motion, lengths, data), "losses": losses,
        "sparse_config": None if sc is None else sc.to_dict(),
    }


def run_ablation(cfg: Dict[str, Any], out: str, data_root: str, device: str = "auto",
                 only: Optional[List[str]] = None, progress: bool = True, log=print) -> List[Dict[str, Any]]:
    import yaml

    from .bench import pick_device

    dev = pick_device(device)
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, "config.yaml"), "w") as f:
        yaml.safe_dump(cfg, f, sort_keys=False)
    data = MotionData(data_root, int(cfg["max_frames"]))
    log(f"ablate: {len(data.train['ids'])} training / {len(data.val['ids'])} validation motions from "
        f"{data_root}; {cfg['steps']} steps x batch {cfg['batch']} per variant on {dev}")
    real_ees = _ees(data.val["x"], data.val["lengths"], data)
    results: List[Dict[str, Any]] = []
    for variant in cfg["variants"]:
        if only and variant["name"] not in only and slug(variant["name"]) not in only:
            continue
        vdir = os.path.join(out, slug(variant["name"]))
        os.makedirs(vdir, exist_ok=True)
        res_path, fail_path = os.path.join(vdir, "result.json"), os.path.join(vdir, "failed.json")
        with open(os.path.join(vdir, "config.json"), "w") as f:
            sc = sparse_config(cfg, variant)
            json.dump({"variant": variant, "sparse_config": None if sc is None else sc.to_dict(),
                       **{k: cfg[k] for k in ("seed", "steps", "batch", "max_frames", "diffusion_steps", "lr",
                                              "model", "eval")}}, f, indent=2)
        if os.path.exists(res_path):
            with open(res_path) as f:
                res = json.load(f)
            log(f"  {variant['name']}: done before, skipped ({res_path})")
            results.append(res)
            continue
        t0 = time.perf_counter()
        try:
            res = run_variant(cfg, variant, data, dev, progress)
            res["wall_s"] = time.perf_counter() - t0
            with open(res_path, "w") as f:
                json.dump(res, f)
            if os.path.exists(fail_path):
                os.remove(fail_path)
            log(f"  {variant['name']}: loss {res['final_loss']:.4f}, {res['steps_per_s']:.2f} steps/s, "
                f"{res['wall_s']:.0f} s")
        except Exception as e:  # recorded, the other variants go on
            res = {"name": variant["name"], "status": "failed", "error": f"{type(e).__name__}: {e}",
                   "traceback": traceback.format_exc(), "wall_s": time.perf_counter() - t0}
            with open(fail_path, "w") as f:
                json.dump(res, f, indent=2)
            log(f"  {variant['name']}: FAILED ({res['error']}); see {fail_path}")
        results.append(res)
    write_report(results, out, real_ees, cfg)
    return results


# ----------------------------------------------------------------------------------------- report
COLUMNS = ("variant", "status", "final loss", "best loss", "val loss", "steps/s", "keyframe error (mm)", "EES (cm/frame)",
           "wall (s)")


def _fmt(v: Any, spec: str) -> str:
    return "—" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def write_report(results: List[Dict[str, Any]], out: str, real_ees: Optional[float], cfg: Dict[str, Any]) -> str:
    rows = []
    for r in results:
        ok = r.get("status") == "ok"
        rows.append([r["name"], r.get("status", "?"),
                     _fmt(r.get("final_loss") if ok else None, ".4f"), _fmt(r.get("best_loss") if ok else None, ".4f"),
                     _fmt(r.get("val_loss") if ok else None, ".4f"),
                     _fmt(r.get("steps_per_s") if ok else None, ".2f"),
                     _fmt(r.get("keyframe_error_mm") if ok else None, ".1f"),
                     _fmt(r.get("ees") if ok else None, ".3f"), _fmt(r.get("wall_s"), ".0f")])
    with open(os.path.join(out, "results.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        w.writerows(rows)
    lines = [f"{cfg.get('name', 'ablation')}: {cfg['steps']} steps × batch {cfg['batch']}, seed {cfg['seed']}, "
             f"TinyMDM {cfg['model']}, {cfg['diffusion_steps']} diffusion steps; sparse base {cfg.get('sparse')}",
             "", "| " + " | ".join(COLUMNS) + " |", "| --- | --- |" + " ---: |" * (len(COLUMNS) - 2)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    try:
        import smdm_plugin.metrics  # noqa: F401

        lines.append(f"\nEES of the real validation motions: {_fmt(real_ees, '.3f')} cm/frame "
                     "(generated motions closer to it are better).")
    except ImportError:
        lines.append("\nEES: smdm_plugin.metrics is not available; column left empty.")
    failed = [r for r in results if r.get("status") != "ok"]
    for r in failed:
        lines.append(f"\n{r['name']} failed: {r.get('error')}")
    text = "\n".join(lines)
    with open(os.path.join(out, "results.md"), "w") as f:
        f.write(text + "\n")
    _plot(results, os.path.join(out, "loss_curves.png"))
    return text


def _plot(results: List[Dict[str, Any]], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 5))
    for r in results:
        if r.get("status") != "ok" or not r.get("losses"):
            continue
        loss = np.asarray(r["losses"])
        k = max(1, len(loss) // 20)
        sm = np.convolve(loss, np.ones(k) / k, mode="valid")
        ax.plot(np.arange(len(sm)) + k, sm, label=r["name"], lw=1.5 if r["name"].startswith(("dense", "sparse")) else 1)
    ax.set_xlabel("training step")
    ax.set_ylabel("training loss (moving average)")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ----------------------------------------------------------------------------------------- CLI
def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="smdm ablate", description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default="table1",
                   help="the grid: a YAML path or a packaged grid name (table1, defaults, quick)")
    p.add_argument("--out", default=os.path.join("results", "ablate"))
    p.add_argument("--data", default=None, help=f"HumanML3D-format folder (default: config 'data' or {DEFAULT_DATA})")
    p.add_argument("--steps", type=int, default=None, help="override the config's steps per variant")
    p.add_argument("--device", default="auto")
    p.add_argument("--only", nargs="+", default=None, help="run only these variants (names or slugs)")
    p.add_argument("--threads", type=int, default=None,
                   help="torch.set_num_threads; 1 is much faster on a CPU shared with other jobs")
    p.add_argument("--no-progress", action="store_true")
    a = p.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    cfg = load_config(a.config)
    if a.steps:
        cfg["steps"] = a.steps
    data_root = a.data or cfg.get("data") or DEFAULT_DATA
    cfg["data"] = data_root
    try:
        results = run_ablation(cfg, a.out, data_root, a.device, a.only, progress=not a.no_progress)
    except FileNotFoundError as e:
        print(str(e), file=sys.stderr)
        return 2
    with open(os.path.join(a.out, "results.md")) as f:
        print("\n" + f.read())
    print(f"results: {os.path.abspath(a.out)}")
    return 0 if all(r.get("status") == "ok" for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
