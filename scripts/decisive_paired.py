"""Paired differences (sparse − dense, per seed) of the decisive study, with 95% Student-t intervals.

Reads the ``results.json`` that ``smdm ablate --config decisive_t{10,50} --out DIR`` (or
``--resume --report-only``) writes in each folder and prints one markdown table per folder: for every
snapshot (equal steps, equal CPU time) and metric, the seeds both variants finished, the dense and
sparse means, and the mean paired difference ``sparse − dense`` ± t(0.975, n−1)·sd/√n (no interval
for one seed). A seed only one variant finished is left out of the pairs.

    python scripts/decisive_paired.py results/decisive_t50 results/decisive_t10 > docs/decisive/paired.md
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from typing import Dict, List, Sequence, Tuple

from smdm_plugin.apps.ablate.study import t_interval

#: (key, label, better): the metrics of the table
METRICS: Sequence[Tuple[str, str, str]] = (
    ("fid", "FID", "↓"), ("r_precision_top3", "R@3", "↑"), ("matching_score", "MM-Dist", "↓"),
    ("jitter_per_speed", "j/s (1/s²)", "→ real"), ("foot_skating", "skating", "↓"))
DENSE, SPARSE = "dense", "sparse (VW)"


def snapshots(run: dict) -> Dict[Tuple[str, float], dict]:
    """``(kind, at) -> snapshot`` of one run record."""
    return {(s["kind"], float(s["at"])): s for s in run.get("snapshots", [])}


def paired(results: dict) -> List[str]:
    """The markdown lines of one study folder's paired table."""
    runs = results["runs"]
    dense = {r["seed"]: snapshots(r) for r in runs.get(DENSE, []) if r.get("status") == "ok"}
    sparse = {r["seed"]: snapshots(r) for r in runs.get(SPARSE, []) if r.get("status") == "ok"}
    seeds = sorted(set(dense) & set(sparse))
    ref = results.get("reference", {})
    lines = [f"### {results['config']['name']} (T = {results['config']['diffusion_steps']}): "
             f"seeds {seeds} ({len(seeds)} paired)", "",
             "| snapshot | metric | dense | sparse (VW) | sparse − dense (95% t-interval) | real |",
             "| --- | --- | ---: | ---: | ---: | ---: |"]
    keys = sorted({k for s in seeds for k in dense[s]} & {k for s in seeds for k in sparse[s]},
                  key=lambda k: (k[0] != "seconds", k[1]))
    for key in keys:
        have = [s for s in seeds if key in dense[s] and key in sparse[s]]
        label = f"{key[1]:g} s cpu" if key[0] == "seconds" else f"{key[1]:g} steps"
        for metric, name, better in METRICS:
            d = [dense[s][key][metric] for s in have]
            p = [sparse[s][key][metric] for s in have]
            diff = [b - a for a, b in zip(d, p)]
            m, hw, n = t_interval(diff)
            ci = f"{m:+.3f} ± {hw:.3f}" if n >= 2 and math.isfinite(hw) else f"{m:+.3f} (n = {n})"
            real = ref.get("fid_train_vs_eval" if metric == "fid" else metric)   # FID: real train vs test
            lines.append(f"| {label} | {name} {better} | {t_interval(d)[0]:.3f} | {t_interval(p)[0]:.3f} | {ci} | "
                         f"{'' if real is None else f'{real:.3f}'} |")
        steps = [(dense[s][key]["step"], sparse[s][key]["step"]) for s in have]
        lines.append(f"| {label} | steps | {sum(a for a, _ in steps) / len(steps):.0f} | "
                     f"{sum(b for _, b in steps) / len(steps):.0f} | | |")
    return lines + [""]


def main(argv: Sequence[str] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folders", nargs="+", help="study results folders (each with results.json)")
    a = p.parse_args(argv)
    out: List[str] = []
    for folder in a.folders:
        path = os.path.join(folder, "results.json")
        try:
            with open(path, encoding="utf-8") as f:
                results = json.load(f)
        except (OSError, ValueError) as e:
            p.exit(1, f"decisive_paired.py: {path}: {e}\n")
        out += paired(results)
    sys.stdout.write("\n".join(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
