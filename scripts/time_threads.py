"""Wall time of ``smdm`` commands with the default thread count vs ``--threads 1`` / ``--threads 2``,
on an idle CPU and with busy-loop neighbours (docs/threads.md).

    python scripts/time_threads.py --workdir /tmp/tt --repeats 3 --neighbours 0 2 \
        [--baseline-pythonpath /path/to/an/older/checkout]

Each command runs in a fresh process (imports included), variants interleaved within each repeat;
the table gives the median and the range in seconds, and the 1-minute load average seen at the
start of each run. ``--neighbours N`` starts N ``python -c 'while True: pass'`` processes for that
condition and kills them after. Needs ``smdm demo``-size models in WORKDIR/full (made first with
``smdm demo --minutes 0.1 --out WORKDIR/full``) and the exported clip WORKDIR/dance.npy.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from typing import Dict, List, Optional, Tuple

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def commands(data: Optional[str]) -> Dict[str, List[str]]:
    cmds = {
        "inbetween (demo-size models, 100 frames)": [
            "inbetween", "--model", "full/dense", "full/sparse", "--keyframes", "dance.npy", "--every", "20", "--length", "100",
            "--no-gif", "--quiet", "--out", "ib", "--overwrite"],
        "demo --quick": ["demo", "--quick", "--no-gif", "--out", "dq", "--overwrite"],
    }
    if data:
        cmds["train, 20 steps (sparse TinyMDM, batch 16)"] = [
            "train", "--data", data, "--steps", "20", "--out", "tr", "--overwrite", "--no-progress", "--sparse"]
    return cmds


def run(args: List[str], pythonpath: str, cwd: str) -> Tuple[float, float]:
    env = dict(os.environ, PYTHONPATH=pythonpath)
    env.pop("OMP_NUM_THREADS", None)
    env.pop("OMP_WAIT_POLICY", None)
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "smdm_plugin", *args], cwd=cwd, env=env,
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, timeout=600)
    dt = time.perf_counter() - t0
    if r.returncode:
        raise SystemExit(f"{args}: exit {r.returncode}: {r.stderr[-500:]}")
    return dt, load


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--workdir", required=True, help="folder with full/{dense,sparse} and dance.npy")
    p.add_argument("--repeats", type=int, default=3, help="runs per cell (median reported)")
    p.add_argument("--neighbours", type=int, nargs="+", default=[0, 2], help="busy-loop processes per condition")
    p.add_argument("--data", default=None, help="HumanML3D-format folder for the train row (optional)")
    p.add_argument("--baseline-pythonpath", default=None,
                   help="an older checkout to time its default as 'before' (optional)")
    p.add_argument("--only", nargs="+", default=None, help="commands to run, by their first word: inbetween, demo, train")
    a = p.parse_args()
    variants: List[Tuple[str, List[str], str]] = [("default", [], ROOT), ("--threads 1", ["--threads", "1"], ROOT),
                                                  ("--threads 2", ["--threads", "2"], ROOT)]
    if a.baseline_pythonpath:
        variants.insert(0, ("before (0.2 default)", [], a.baseline_pythonpath))
    rows = []
    for n in a.neighbours:
        procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
        try:
            time.sleep(1.0 if n else 0.0)
            for label, cmd in commands(a.data).items():
                if a.only and label.split()[0].rstrip(",") not in [o.rstrip(",") for o in a.only]:
                    continue
                times: Dict[str, List[float]] = {v[0]: [] for v in variants}
                loads: List[float] = []
                for _ in range(a.repeats):
                    for name, extra, path in variants:
                        dt, load = run(cmd + extra, path, a.workdir)
                        times[name].append(dt)
                        loads.append(load)
                        print(f"{n} neighbours | {label} | {name}: {dt:.1f} s (load {load:.1f})", flush=True)
                rows.append((n, label, times, loads))
        finally:
            for q in procs:
                q.kill()
                q.wait()
    names = [v[0] for v in variants]
    print("\n| neighbours | command | " + " | ".join(names) + " | load at start |")
    print("| ---: | --- |" + " ---: |" * len(names) + " ---: |")
    for n, label, times, loads in rows:
        cells = [f"{statistics.median(t):.1f} ({min(t):.1f}–{max(t):.1f})" for t in (times[k] for k in names)]
        print(f"| {n} | {label} | " + " | ".join(cells) + f" | {min(loads):.1f}–{max(loads):.1f} |")


if __name__ == "__main__":
    main()
