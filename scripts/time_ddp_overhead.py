"""What ``torchrun --nproc_per_node 1`` (DistributedDataParallel over one process) costs against a
plain single-process run of ``smdm train``: the same training twice, steps/s from each run's
``result.json`` (training loop only, start-up excluded), and their ratio.

    python scripts/time_ddp_overhead.py --data /path/to/HumanML3D [--device cuda] [--steps 300]
        [--batch 64] [--sparse] [--repeats 2] [-- extra smdm train options]

Prints a markdown table and a JSON line. On a GPU machine this is the "1 GPU vs
--nproc_per_node 1" measurement of docs/distributed.md.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile


def run(launcher: list, args: argparse.Namespace, extra: list, out: str) -> dict:
    cmd = launcher + ["train", "--data", args.data, "--out", out, "--steps", str(args.steps), "--batch",
                      str(args.batch), "--device", args.device, "--no-progress", "--overwrite"]
    cmd += (["--sparse"] if args.sparse else []) + extra
    env = dict(os.environ)
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = repo + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
    with open(os.path.join(out, "result.json")) as f:
        return json.load(f)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True)
    p.add_argument("--device", default="auto")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--sparse", action="store_true")
    p.add_argument("--repeats", type=int, default=2, help="runs of each kind, alternating (best is kept)")
    a = p.parse_args(argv)
    plain = [sys.executable, "-m", "smdm_plugin"]
    ddp = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "1", "-m", "smdm_plugin"]
    best = {"plain": 0.0, "torchrun-1": 0.0}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.repeats):
            for name, launcher in (("plain", plain), ("torchrun-1", ddp)):
                res = run(launcher, a, extra, os.path.join(tmp, f"{name}{r}"))
                best[name] = max(best[name], res["steps_per_s"])
    ratio = best["torchrun-1"] / best["plain"]
    print("| run | steps/s (best of %d) |\n| --- | ---: |" % a.repeats)
    for name, v in best.items():
        print(f"| {name} | {v:.3f} |")
    print(f"\ntorchrun --nproc_per_node 1 / plain: {ratio:.3f}")
    print(json.dumps({"device": a.device, "steps": a.steps, "batch": a.batch, "sparse": a.sparse,
                      "steps_per_s": best, "ratio": ratio}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
