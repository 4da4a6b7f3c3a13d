"""Start sparse from a dense checkpoint, measured (docs/mdm.md, "Start from a dense checkpoint").

(i)  zero-shot wrap vs dense: a dense TinyMDM trained ``--dense-steps`` (one per seed), sampled dense
     and wrapped sparse (preset zero_shot, 80% and 50% of the frames dropped): FID, jitter per unit
     speed, foot skating (``smdm eval``, 3 replications each) and sampling time.
(ii) warm start at equal total optimiser steps S = dense-steps + more-steps: (a) sparse from
     scratch for S steps (then on, to see when it catches (b)), (b) sparse warm-started from the
     dense model (``smdm train --init-from``) for more-steps, (c) dense continued for more-steps.

Every run is ``smdm train`` / ``smdm eval`` with ``--threads 1``, one after the other.

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


def train(data: str, out: str, steps: int, seed: int, extra: List[str] = (), resume: bool = False) -> None:
    sh(["train", "--data", data, "--out", out, "--steps", str(steps), "--seed", str(seed), "--threads", "1",
        "--no-progress"] + (["--resume"] if resume else ["--overwrite"]) + list(extra))


def evaluate(a: argparse.Namespace, model: str, out: str, replications: int) -> Dict[str, Any]:
    sh(["eval", "--data", a.data, "--evaluator", a.evaluator, "--model", model, "--out", out, "--overwrite",
        "--replications", str(replications), "--mm-repeats", "0", "--threads", "1"])
    with open(os.path.join(out, "metrics.json")) as f:
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
    from smdm_plugin.core.config import load_preset
    from smdm_plugin.io.checkpoint import save_sparse_config
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


def mean_ci(values: List[float]) -> str:
    v = np.asarray([x for x in values if x is not None], float)
    if len(v) == 0:
        return "-"
    if len(v) == 1:
        return f"{v[0]:.3g}"
    half = 1.96 * v.std(ddof=1) / np.sqrt(len(v))
    return f"{v.mean():.3g} ± {half:.2g}"


def tables(res: Dict[str, Any]) -> str:
    """The two markdown tables of docs/mdm.md from the results JSON."""
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
        out += [f"(i) zero-shot wrap vs dense: mean ± 95% interval over {n} seed(s) (one dense model per seed, "
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
        out += ["", "(ii) warm start at equal optimiser steps: mean ± 95% interval over 3 smdm eval replications",
                "", "| run | steps | FID | jitter per speed | foot skating |", "| --- | --- | ---: | ---: | ---: |"]
        label = {"b_warm": "(b) sparse, warm-started from the dense model", "c_dense_continued": "(c) dense, continued"}
        order = sorted(w, key=lambda k: (k.startswith("a_"), int(k.rsplit("_", 1)[1]) if k.startswith("a_") else 0))
        for key in order:
            r = w[key]
            name = r.get("label") or label.get(key, "(a) sparse from scratch")
            out.append(f"| {name} | {r['steps']} | " + " | ".join(cell(r[k]) for k in METRICS) + " |")
    return "\n".join(out) + "\n"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True)
    p.add_argument("--evaluator", required=True)
    p.add_argument("--work", required=True, help="folder for the runs (replaced)")
    p.add_argument("--out", required=True, help="results JSON (a .md table beside it)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--dense-steps", type=int, default=400)
    p.add_argument("--more-steps", type=int, default=200)
    p.add_argument("--catch-up", type=int, nargs="*", default=[600],
                   help="(a) evaluated again after this many more steps each")
    p.add_argument("--replications", type=int, default=3, help="smdm eval replications in (ii) (default 3)")
    p.add_argument("--zero-shot-replications", type=int, default=1,
                   help="smdm eval replications per seed in (i) (default 1: the interval is over the seeds)")
    p.add_argument("--skip", nargs="*", default=[], choices=["zero_shot", "warm"])
    p.add_argument("--tables-only", action="store_true", help="print the tables of an existing --out and stop")
    p.add_argument("--add-scratch", type=int, nargs="*", default=[],
                   help="add (a) rows at these step counts (separate from-scratch runs) to an existing --out")
    p.add_argument("--retime", type=int, default=0,
                   help="re-measure the sampling times of an existing --out: this many rounds, the models "
                        "of a seed interleaved (median)")
    a = p.parse_args()
    if a.tables_only:
        with open(a.out) as f:
            print(tables(json.load(f)), end="")
        return 0
    os.makedirs(a.work, exist_ok=True)
    res: Dict[str, Any] = {"settings": vars(a), "zero_shot": {}, "warm": {}}
    if a.add_scratch or a.retime:
        with open(a.out) as f:
            res = json.load(f)

    def save() -> None:
        with open(a.out, "w") as f:
            json.dump(res, f, indent=2)

    W = lambda *n: os.path.join(a.work, *n)  # noqa: E731
    def zero_shot(seed: int) -> None:                             # (i)
        row: Dict[str, Any] = {}
        for name, reduction in (("dense", None), ("zero_shot_80", 0.8), ("zero_shot_50", 0.5)):
            folder = W(f"dense_s{seed}") if reduction is None else W(f"{name}_s{seed}")
            if reduction is not None:
                wrap_folder(W(f"dense_s{seed}"), folder, reduction)
            m = pick(evaluate(a, folder, W(f"eval_{name}_s{seed}"), a.zero_shot_replications))
            m["sampling_s"] = sampling_seconds(folder)
            row[name] = m
            res["zero_shot"][f"seed{seed}"] = row
            save()

    def warm(seed: int) -> None:                                  # (ii)
        S = a.dense_steps + a.more_steps
        dense = W(f"dense_s{seed}")
        t0 = time.time()
        train(a.data, W("warm_b"), a.more_steps, seed + 100, ["--sparse", "--init-from", dense])
        res["warm"]["b_warm"] = {"steps": f"{a.dense_steps} dense + {a.more_steps} sparse",
                                 "wall_s": time.time() - t0,
                                 **pick(evaluate(a, W("warm_b"), W("eval_warm_b"), a.replications))}
        save()
        for key, run, extra, label in VARIANTS:               # which new layer limits the warm start
            train(a.data, W(run), a.more_steps, seed + 100 if key.startswith("b") else seed,
                  [x.replace("DENSE", dense) for x in extra])
            res["warm"][key] = {"steps": f"{a.dense_steps} dense + {a.more_steps} sparse" if key.startswith("b")
                                else f"{a.more_steps} sparse", "label": label,
                                **pick(evaluate(a, W(run), W("eval_" + run), a.replications))}
            save()
        t0 = time.time()
        train(a.data, W("dense_c"), a.more_steps, seed + 100, ["--init-from", dense])
        res["warm"]["c_dense_continued"] = {"steps": f"{S} dense", "wall_s": time.time() - t0,
                                            **pick(evaluate(a, W("dense_c"), W("eval_dense_c"), a.replications))}
        save()
        steps = S
        train(a.data, W("scratch_a"), steps, seed, ["--sparse"])
        res["warm"][f"a_scratch_{steps}"] = {"steps": f"{steps} sparse",
                                            **pick(evaluate(a, W("scratch_a"), W(f"eval_scratch_{steps}"),
                                                            a.replications))}
        save()
        for more in a.catch_up:
            steps = S + more
            train(a.data, W("scratch_a"), steps, seed, ["--sparse"], resume=True)
            res["warm"][f"a_scratch_{steps}"] = {"steps": f"{steps} sparse",
                                                **pick(evaluate(a, W("scratch_a"), W(f"eval_scratch_{steps}"),
                                                                a.replications))}
            save()

    if a.add_scratch or a.retime:
        for n in a.add_scratch:
            train(a.data, W(f"scratch_{n}"), n, a.seeds[0], ["--sparse"])
            res["warm"][f"a_scratch_{n}"] = {"steps": f"{n} sparse", **pick(
                evaluate(a, W(f"scratch_{n}"), W(f"eval_scratch_p{n}"), a.replications))}
            save()
        for key, row in res["zero_shot"].items() if a.retime else ():
            seed = key[len("seed"):]
            folders = {n: W(f"dense_s{seed}") if n == "dense" else W(f"{n}_s{seed}") for n in row}
            times: Dict[str, List[float]] = {n: [] for n in row}
            for _ in range(a.retime):
                for n, folder in folders.items():
                    times[n].append(sampling_seconds(folder))
            for n in row:
                row[n]["sampling_s"] = float(np.median(times[n]))
            save()
        text = tables(res)
        with open(os.path.splitext(a.out)[0] + ".md", "w") as f:
            f.write(text)
        print(text, end="")
        return 0
    for i, seed in enumerate(a.seeds):                            # dense models, then what starts from them
        if not os.path.exists(W(f"dense_s{seed}", f"model{a.dense_steps:09d}.pt")):
            train(a.data, W(f"dense_s{seed}"), a.dense_steps, seed)
        if "zero_shot" not in a.skip:
            zero_shot(seed)
        if i == 0 and "warm" not in a.skip:
            warm(seed)
    save()
    text = tables(res)
    with open(os.path.splitext(a.out)[0] + ".md", "w") as f:
        f.write(text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
