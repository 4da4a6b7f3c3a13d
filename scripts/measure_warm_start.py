"""Start sparse from a dense checkpoint, measured (docs/mdm.md, "Start from a dense checkpoint").

(i)  zero-shot wrap vs dense: a dense TinyMDM trained ``--dense-steps`` (one per seed), sampled dense
     and wrapped sparse (preset zero_shot, 80% and 50% of the frames dropped): FID, jitter per unit
     speed, foot skating (``smdm eval``, 3 replications each) and sampling time.
(ii) warm start at equal total optimiser steps S = dense-steps + more-steps, for every seed: (a) sparse
     from scratch at --scratch-steps and S steps (and at S + --catch-up where it has not caught (b)
     on FID, or for --catch-up-seeds), (b) sparse warm-started from the dense model (``smdm train
     --init-from``) for more-steps, (c) dense continued for more-steps; reported as mean ± 95%
     t-interval over the seeds, with the paired differences (b)-(a) and (b)-(c) and the step at
     which (a) catches (b) per seed. The ablations (b'), (b''), (a'') run for --variant-seeds only.

Every run is ``smdm train`` / ``smdm eval`` with ``--threads 1``, one after the other, in per-seed
folders of --work (``warm_b_s{seed}``, ``dense_c_s{seed}``, ``scratch_a_s{seed}``, ...). A run whose
folder already holds its final checkpoint (same seed) and an evaluation whose metrics.json scored that
model after its checkpoint was written are reused, and an existing --out is updated, so an
interrupted measurement resumes where it stopped.

    python scripts/measure_warm_start.py --data ../shared/data/cmu-humanml3d-large \\
        --evaluator EVAL_DIR --work runs/warm --out docs/warm_start_results.json
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from typing import Any, Dict, List

import numpy as np

PY = sys.executable
METRICS = ("fid", "jitter_per_speed", "foot_skating")


#: (ii)'s variants: (key, run folder, smdm train options, table label)
VARIANTS = (
    ("b_warm_amp1", "warm_amp1.0", ["--sparse", "--init-from", "DENSE", "--init-amplitude", "1.0"],
     "(b') warm start, fitted sine layers at 1 rad (--init-amplitude 1.0)"),
    ("b_warm_nofsq", "warm_nofsq", ["--sparse", "--sparse_fsq", "false", "--init-from", "DENSE"],
     "(b'') warm start without FSQ keys (--sparse_fsq false)"),
    ("a_scratch_nofsq_200", "scratch_nofsq_200", ["--sparse", "--sparse_fsq", "false"],
     "(a'') sparse from scratch without FSQ keys"),
)


def sh(args: List[str]) -> None:
    t0 = time.time()
    print("$ smdm " + " ".join(args), flush=True)
    subprocess.run([PY, "-m", "smdm_plugin"] + args, check=True, stdout=subprocess.DEVNULL)
    print(f"  ({time.time() - t0:.0f} s)", flush=True)


def checkpoints(folder: str) -> Dict[int, str]:
    """``{step: path}`` of the ``model*.pt`` checkpoints in a run folder (empty if there is none)."""
    if not os.path.isdir(folder):
        return {}
    return {int(n[len("model"):-len(".pt")]): os.path.join(folder, n) for n in os.listdir(folder)
            if n.startswith("model") and n.endswith(".pt") and n[len("model"):-len(".pt")].isdigit()}


def train(data: str, out: str, steps: int, seed: int, extra: List[str] = (), resume: bool = False) -> None:
    """``smdm train`` to ``steps``; reused when ``out`` already holds that checkpoint from the same seed."""
    if steps in checkpoints(out):
        with open(os.path.join(out, "train_config.json")) as f:
            if int(json.load(f)["seed"]) == seed:
                print(f"$ (reusing {out}, step {steps})", flush=True)
                return
    sh(["train", "--data", data, "--out", out, "--steps", str(steps), "--seed", str(seed), "--threads", "1",
        "--no-progress"] + (["--resume"] if resume else ["--overwrite"]) + list(extra))


def steps_per_s(run: str) -> float:
    """Training speed of a run (its result.json; 1 thread, on a CPU shared with other jobs)."""
    with open(os.path.join(run, "result.json")) as f:
        return float(json.load(f)["steps_per_s"])


def evaluate(a: argparse.Namespace, model: str, out: str, replications: int, steps: int) -> Dict[str, Any]:
    """``smdm eval`` of the model folder at checkpoint ``steps`` (its latest). An existing ``out`` is
    reused when it scored this folder with ``replications`` after ``steps``'s checkpoint was written
    and before any later one was."""
    ckpt = checkpoints(model)
    if steps not in ckpt:
        raise SystemExit(f"measure_warm_start: {model} has no checkpoint at step {steps}")
    done = os.path.join(out, "metrics.json")
    if os.path.exists(done):
        with open(done) as f:
            m = json.load(f)
        t = os.path.getmtime(done)
        if (os.path.realpath(m["source"]["model"]) == os.path.realpath(model) and m["replications"] == replications
                and os.path.getmtime(ckpt[steps]) <= t
                and all(os.path.getmtime(p) > t for s, p in ckpt.items() if s > steps)):
            print(f"$ (reusing {out})", flush=True)
            return m
    if max(ckpt) != steps:
        raise SystemExit(f"measure_warm_start: {model} holds a checkpoint after step {steps}; smdm eval would "
                         f"score that one (remove {out} only together with the later checkpoints)")
    sh(["eval", "--data", a.data, "--evaluator", a.evaluator, "--model", model, "--out", out, "--overwrite",
        "--replications", str(replications), "--mm-repeats", "0", "--threads", "1",
        "--protocol", "fixed"])   # the protocol the published tables used (0.4's; docs/mdm.md)
    with open(done) as f:
        return json.load(f)
def pick(metrics: Dict[str, Any]) -> Dict[str, Any]:
    """FID, jitter per unit speed and foot skating of the model: ``{name: [mean, 95% interval half-width]}``
    over the replications, and the real motions' values (``real_<name>``)."""
    out: Dict[str, Any] = {}
    for k in METRICS:
        m = metrics["metrics"][k]
        out[k] = [m["mean"], m["interval"]]
        out["real_" + k] = metrics["real"].get(k)
    return out


def wrap_folder(dense: str, out: str, reduction: float) -> None:
    """A model folder holding the dense checkpoint wrapped sparse (preset zero_shot): the same
    weights, the marker buffer, sparse_config.json (what ``smdm eval --model`` reads)."""
    import torch

    from smdm_plugin.adapters.warm import wrap_dense
    from smdm_plugin.core.presets import load_preset
    from smdm_plugin.adapters.checkpoint import save_sparse_config
    from smdm_plugin.training.trainer import load_trained

    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(dense, out, ignore=shutil.ignore_patterns("model*.pt", "train_state.pt"))
    model, _ = load_trained(dense)
    mean, std = np.load(os.path.join(dense, "Mean.npy")), np.load(os.path.join(dense, "Std.npy"))
    with open(os.path.join(dense, "train_config.json")) as f:
        steps = int(json.load(f)["diffusion_steps"])
    wrap_dense(model, load_preset("zero_shot").replace(reduction=reduction, diffusion_steps=steps), mean=mean,
               std=std, origin=dense)
    last = sorted(n for n in os.listdir(dense) if n.startswith("model") and n.endswith(".pt"))[-1]
    torch.save(model.state_dict(), os.path.join(out, last))
    save_sparse_config(model, out, overwrite=True)
    with open(os.path.join(out, "train_config.json")) as f:
        tc = json.load(f)
    tc["sparse"] = json.loads(open(os.path.join(out, "sparse_config.json")).read())
    tc["wrapped_from"] = os.path.abspath(dense)
    with open(os.path.join(out, "train_config.json"), "w") as f:
        json.dump(tc, f, indent=2)


def sampling_seconds(folder: str, n: int = 8, frames: int = 120, repeats: int = 1) -> float:
    """Median wall time (s) of generating ``n`` motions of ``frames`` frames (one batch, 1 thread)."""
    import torch

    from smdm_plugin.apps.evaluate import Generator

    torch.set_num_threads(1)
    g = Generator(folder, torch.device("cpu"))
    times = []
    for r in range(repeats):
        t0 = time.perf_counter()
        g.generate([frames] * n, seed=r, batch=n)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def t_interval(values: List[float]) -> List[Any]:
    """``[mean, 95% t-interval half-width, n]`` of the values (half-width None for one value)."""
    from scipy import stats

    v = np.asarray(values, float)
    if len(v) < 2:
        return [float(v.mean()), None, len(v)]
    return [float(v.mean()), float(stats.t.ppf(0.975, len(v) - 1) * v.std(ddof=1) / np.sqrt(len(v))), len(v)]


def mean_ci(values: List[float]) -> str:
    v = [x for x in values if x is not None]
    if not v:
        return "-"
    m, half, _ = t_interval(v)
    return f"{m:.3g}" if half is None else f"{m:.3g} ± {half:.2g}"


def upgrade(res: Dict[str, Any]) -> Dict[str, Any]:
    """Results of the one-seed version (``warm`` keyed by run) as ``warm: {"seed<first>": {...}}``."""
    w = res.get("warm", {})
    if w and not all(k.startswith("seed") for k in w):
        res["warm"] = {f"seed{res['settings']['seeds'][0]}": w}
    return res


def scratch_steps(row: Dict[str, Any]) -> Dict[int, Dict[str, Any]]:
    """``{steps: metrics}`` of a seed's (a) runs (sparse from scratch, the recipe's defaults)."""
    return {int(k.rsplit("_", 1)[1]): r for k, r in row.items()
            if k.startswith("a_scratch_") and k[len("a_scratch_"):].isdigit()}


def summarize(res: Dict[str, Any]) -> Dict[str, Any]:
    """(ii) over the seeds: ``runs`` {key: {seeds, steps, label, metric: [mean, half, n]}}, ``differences``
    {name: {seeds, metric: [mean, half, n]}} (paired by seed) and ``catch_up`` {seed: {metric: step of (a)
    that first reaches (b)'s mean over the replications, or None}}; metrics are each seed's means."""
    w = res.get("warm", {})
    s = res["settings"]
    S, more = s["dense_steps"] + s["more_steps"], s["more_steps"]
    keys: List[str] = []
    for row in w.values():
        keys += [k for k in row if k not in keys]
    runs = {}
    for k in keys:
        rows = {seed: row[k] for seed, row in w.items() if k in row}
        first = next(iter(rows.values()))
        runs[k] = {"seeds": [int(x[len("seed"):]) for x in rows], "steps": first["steps"],
                   "label": first.get("label"), **{m: t_interval([r[m][0] for r in rows.values()]) for m in METRICS}}
    diffs = {}
    for name, x, y in ((f"(b) - (a) at {S} steps", "b_warm", f"a_scratch_{S}"),
                       ("(b) - (c)", "b_warm", "c_dense_continued"),
                       (f"(b) - (a) at {more} steps (the dense model counted as free)", "b_warm", f"a_scratch_{more}")):
        pairs = [(seed, row[x], row[y]) for seed, row in w.items() if x in row and y in row]
        if pairs:
            diffs[name] = {"seeds": [int(p[0][len("seed"):]) for p in pairs],
                           **{m: t_interval([p[1][m][0] - p[2][m][0] for p in pairs]) for m in METRICS}}
    catch = {}
    for seed, row in w.items():
        if "b_warm" in row:
            a = scratch_steps(row)
            catch[seed] = {m: next((n for n in sorted(a) if a[n][m][0] <= row["b_warm"][m][0]), None)
                           for m in ("fid", "foot_skating")}
    return {"runs": runs, "differences": diffs, "catch_up": catch}


def tables(res: Dict[str, Any]) -> str:
    """The markdown tables of docs/mdm.md from the results JSON."""
    def cell(v: Any) -> str:
        if v is None:
            return "-"
        if isinstance(v, list):
            return f"{v[0]:.3g} ± {v[1]:.2g}" if v[1] else f"{v[0]:.3g}"
        return f"{v:.3g}"

    out = []
    zs = res.get("zero_shot", {})
    if zs:
        n = len(zs)
        out += [f"(i) zero-shot wrap vs dense: mean ± 95% t-interval over {n} seed(s) (one dense model per seed, "
                "one smdm eval replication each)", "",
                "| model | FID | jitter per speed | foot skating | sampling s (8 x 120 frames) |",
                "| --- | ---: | ---: | ---: | ---: |"]
        names = (("dense", "dense"), ("zero_shot_80", "zero-shot wrap, 80% dropped"),
                 ("zero_shot_50", "zero-shot wrap, 50% dropped"))
        for key, label in names:
            rows = [r[key] for r in zs.values() if key in r]
            if not rows:
                continue
            out.append(f"| {label} | " + " | ".join(mean_ci([r[k][0] for r in rows]) for k in METRICS)
                       + f" | {mean_ci([r['sampling_s'] for r in rows])} |")
        out += ["", "per seed: FID / jitter per speed / foot skating", "",
                "| seed | " + " | ".join(label for _, label in names) + " |", "| --- |" + " ---: |" * len(names)]
        for seed, r in zs.items():
            out.append(f"| {seed[len('seed'):]} | " + " | ".join(
                " / ".join(f"{r[k][m][0]:.3g}" for m in METRICS) if k in r else "-" for k, _ in names) + " |")
        out.append("")
        real = next(iter(zs.values()))["dense"]
        out.append(f"real (test split): jitter per speed {cell(real['real_jitter_per_speed'])}, foot skating "
                   f"{cell(real['real_foot_skating'])}")
    w = res.get("warm", {})
    if w:
        sm = summarize(res)
        label = {"b_warm": "(b) sparse, warm-started from the dense model", "c_dense_continued": "(c) dense, continued"}
        out += ["", "(ii) warm start at equal optimiser steps: mean ± 95% t-interval over the seeds (each seed: the "
                "mean of 3 smdm eval replications; a row of one seed: ± the replications' 95% interval)", "",
                "| run | steps | seeds | FID | jitter per speed | foot skating |",
                "| --- | --- | --- | ---: | ---: | ---: |"]
        order = sorted(sm["runs"], key=lambda k: (k.startswith("a_"), int(k.rsplit("_", 1)[1]) if k.startswith("a_")
                                                  else 0))
        for key in order:
            r = sm["runs"][key]
            name = r["label"] or label.get(key, "(a) sparse from scratch")
            if len(r["seeds"]) == 1:
                one = w[f"seed{r['seeds'][0]}"][key]
                vals = [cell(one[m]) for m in METRICS]
            else:
                vals = [cell(r[m]) for m in METRICS]
            out.append(f"| {name} | {r['steps']} | {', '.join(map(str, r['seeds']))} | " + " | ".join(vals) + " |")
        out += ["", "paired differences over the seeds (negative FID / skating: (b) better)", "",
                "| difference | seeds | FID | jitter per speed | foot skating |", "| --- | --- | ---: | ---: | ---: |"]
        for name, d in sm["differences"].items():
            out.append(f"| {name} | {', '.join(map(str, d['seeds']))} | " + " | ".join(cell(d[m]) for m in METRICS)
                       + " |")
        steps = sorted({n for row in w.values() for n in scratch_steps(row)})
        out += ["", "per seed: FID / jitter per speed / foot skating; catch-up: the first step count of (a) whose "
                "FID (skating) is at or below (b)'s", "",
                "| seed | (b) | (c) | " + " | ".join(f"(a) {n}" for n in steps)
                + " | catch-up FID | catch-up skating |",
                "| --- |" + " ---: |" * (len(steps) + 4)]
        def trio(r: Any) -> str:
            return " / ".join(f"{r[m][0]:.3g}" for m in METRICS) if r else "-"
        for seed, row in w.items():
            a = scratch_steps(row)
            c = sm["catch_up"].get(seed, {})
            fmt = lambda n: "-" if n is None else f"≤ {n}" if n == min(a) else str(n)  # noqa: E731
            out.append(f"| {seed[len('seed'):]} | {trio(row.get('b_warm'))} | {trio(row.get('c_dense_continued'))} | "
                       + " | ".join(trio(a.get(n)) for n in steps)
                       + f" | {fmt(c.get('fid')) if c.get('fid') is not None else '> ' + str(max(a))} | "
                       + f"{fmt(c.get('foot_skating')) if c.get('foot_skating') is not None else '> ' + str(max(a))} |")
    return "\n".join(out) + "\n"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True)
    p.add_argument("--evaluator", required=True)
    p.add_argument("--work", required=True, help="folder for the runs (finished runs in it are reused)")
    p.add_argument("--out", required=True, help="results JSON, updated if it exists (a .md table beside it)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--dense-steps", type=int, default=400)
    p.add_argument("--more-steps", type=int, default=200)
    p.add_argument("--scratch-steps", type=int, nargs="*", default=[200, 400],
                   help="(a) also trained (separate runs) to these step counts, to see where it catches (b)")
    p.add_argument("--catch-up", type=int, nargs="*", default=[600],
                   help="(a) evaluated again after this many more steps each, for a seed where (a) at S has not "
                        "caught (b) on FID or that is in --catch-up-seeds")
    p.add_argument("--catch-up-seeds", type=int, nargs="*", default=[0])
    p.add_argument("--variant-seeds", type=int, nargs="*", default=[0],
                   help="seeds for which the ablations (b'), (b''), (a'') run")
    p.add_argument("--replications", type=int, default=3, help="smdm eval replications in (ii) (default 3)")
    p.add_argument("--zero-shot-replications", type=int, default=1,
                   help="smdm eval replications per seed in (i) (default 1: the interval is over the seeds)")
    p.add_argument("--skip", nargs="*", default=[], choices=["zero_shot", "warm"])
    p.add_argument("--tables-only", action="store_true", help="print the tables of an existing --out and stop")
    p.add_argument("--retime", type=int, default=0,
                   help="re-measure the sampling times of an existing --out: this many rounds, the models "
                        "of a seed interleaved (median), and stop")
    a = p.parse_args()
    if a.tables_only:
        with open(a.out) as f:
            print(tables(upgrade(json.load(f))), end="")
        return 0
    os.makedirs(a.work, exist_ok=True)
    res: Dict[str, Any] = {"settings": vars(a), "zero_shot": {}, "warm": {}}
    if os.path.exists(a.out):
        with open(a.out) as f:
            res = upgrade(json.load(f))
        res["settings"] = vars(a)

    def save() -> None:
        if res.get("warm"):
            res["warm_summary"] = summarize(res)
        tmp = a.out + ".tmp"
        with open(tmp, "w") as f:
            json.dump(res, f, indent=2)
        os.replace(tmp, a.out)

    W = lambda *n: os.path.join(a.work, *n)  # noqa: E731
    def zero_shot(seed: int) -> None:                             # (i)
        row: Dict[str, Any] = {}
        for name, reduction in (("dense", None), ("zero_shot_80", 0.8), ("zero_shot_50", 0.5)):
            folder = W(f"dense_s{seed}") if reduction is None else W(f"{name}_s{seed}")
            if reduction is not None:
                wrap_folder(W(f"dense_s{seed}"), folder, reduction)
            m = pick(evaluate(a, folder, W(f"eval_{name}_s{seed}"), a.zero_shot_replications, a.dense_steps))
            m["sampling_s"] = sampling_seconds(folder)
            row[name] = m
            res["zero_shot"][f"seed{seed}"] = row
            save()

    def warm(seed: int) -> None:                                  # (ii), folders *_s{seed}
        S = a.dense_steps + a.more_steps
        dense = W(f"dense_s{seed}")
        r = res["warm"].setdefault(f"seed{seed}", {})
        warm_steps = f"{a.dense_steps} dense + {a.more_steps} sparse"
        train(a.data, W(f"warm_b_s{seed}"), a.more_steps, seed + 100, ["--sparse", "--init-from", dense])
        r["b_warm"] = {"steps": warm_steps, "steps_per_s": steps_per_s(W(f"warm_b_s{seed}")), **pick(evaluate(
            a, W(f"warm_b_s{seed}"), W(f"eval_warm_b_s{seed}"), a.replications, a.more_steps))}
        save()
        train(a.data, W(f"dense_c_s{seed}"), a.more_steps, seed + 100, ["--init-from", dense])
        r["c_dense_continued"] = {"steps": f"{S} dense", "steps_per_s": steps_per_s(W(f"dense_c_s{seed}")),
                                  **pick(evaluate(a, W(f"dense_c_s{seed}"), W(f"eval_dense_c_s{seed}"),
                                                  a.replications, a.more_steps))}
        save()
        train(a.data, W(f"scratch_a_s{seed}"), S, seed, ["--sparse"])
        r[f"a_scratch_{S}"] = {"steps": f"{S} sparse", **pick(evaluate(
            a, W(f"scratch_a_s{seed}"), W(f"eval_scratch_{S}_s{seed}"), a.replications, S))}
        save()
        for n in a.scratch_steps:                                 # where (a) catches (b), below S
            train(a.data, W(f"scratch_{n}_s{seed}"), n, seed, ["--sparse"])
            r[f"a_scratch_{n}"] = {"steps": f"{n} sparse", **pick(evaluate(
                a, W(f"scratch_{n}_s{seed}"), W(f"eval_scratch_p{n}_s{seed}"), a.replications, n))}
            save()
        if seed in a.catch_up_seeds or r[f"a_scratch_{S}"]["fid"][0] > r["b_warm"]["fid"][0]:
            for more in a.catch_up:                               # and beyond S
                steps = S + more
                train(a.data, W(f"scratch_a_s{seed}"), steps, seed, ["--sparse"], resume=True)
                r[f"a_scratch_{steps}"] = {"steps": f"{steps} sparse", **pick(evaluate(
                    a, W(f"scratch_a_s{seed}"), W(f"eval_scratch_{steps}_s{seed}"), a.replications, steps))}
                save()
        for key, run, extra, label in VARIANTS if seed in a.variant_seeds else ():   # which new layer limits it
            b = key.startswith("b")
            train(a.data, W(f"{run}_s{seed}"), a.more_steps, seed + 100 if b else seed,
                  [x.replace("DENSE", dense) for x in extra])
            r[key] = {"steps": warm_steps if b else f"{a.more_steps} sparse", "label": label, **pick(
                evaluate(a, W(f"{run}_s{seed}"), W(f"eval_{run}_s{seed}"), a.replications, a.more_steps))}
            save()

    if a.retime:
        for key, row in res["zero_shot"].items():
            seed = key[len("seed"):]
            folders = {n: W(f"dense_s{seed}") if n == "dense" else W(f"{n}_s{seed}") for n in row}
            times: Dict[str, List[float]] = {n: [] for n in row}
            for _ in range(a.retime):
                for n, folder in folders.items():
                    times[n].append(sampling_seconds(folder))
            for n in row:
                row[n]["sampling_s"] = float(np.median(times[n]))
            save()
    else:
        for seed in a.seeds:                                      # dense models, then what starts from them
            if not os.path.exists(W(f"dense_s{seed}", f"model{a.dense_steps:09d}.pt")):
                train(a.data, W(f"dense_s{seed}"), a.dense_steps, seed)
            if "zero_shot" not in a.skip:
                zero_shot(seed)
            if "warm" not in a.skip:
                warm(seed)
    save()
    text = tables(res)
    with open(os.path.splitext(a.out)[0] + ".md", "w") as f:
        f.write(text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
