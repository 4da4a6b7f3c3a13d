"""Train ``smdm evaluator train``'s recipe with several seeds and check, on every one, that its
held-out R-precision falls for time-reversed motion and for swapped captions (the full version of
``tests/metrics/test_evaluator_order.py``'s check; tens of minutes per seed on one CPU thread).

    python scripts/evaluator_seeds.py --data ../shared/data/cmu-humanml3d-large --out results/evaluator_seeds
    python scripts/evaluator_seeds.py --data ... --out ... --save      # also write smdm_plugin/data/evaluator_seeds.json

Each seed is one ``smdm evaluator train --data DATA --out OUT/seed<k> --seed k`` (extra options after
``--``, e.g. ``-- --epochs 60``; an interrupted seed continues with ``--resume``, a finished one is
read back), whose summary holds the check (``retrieval_check`` in ``evaluator.json``: 20 replications
of smdm eval's protocol on the test split, paired drops). Prints the table of
:class:`smdm_plugin.metrics.evaluator.seeds.SeedTable` (per seed, then the spread) and writes
``OUT/seeds.json``; ``--save`` also writes the packaged table that ``smdm evaluator train`` shows and
docs/evaluation.md reproduces.

Exit status: 0 every seed's R-precision falls clearly (95% interval of the paired drop above 0) for
both; 1 some seed's does not (named); 2 bad arguments or a seed's training failed.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from typing import List, Optional, Sequence


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: List[str] = []
    if "--" in argv:
        extra, argv = argv[argv.index("--") + 1:], argv[:argv.index("--")]
    p = argparse.ArgumentParser(prog="evaluator_seeds.py", description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="HumanML3D-format folder with train / val / test splits")
    p.add_argument("--out", required=True, help="folder for the evaluators (OUT/seed<k>) and seeds.json")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="training seeds (default: 0 1 2)")
    p.add_argument("--threads", type=int, default=1, help="CPU threads per training (default: 1)")
    p.add_argument("--save", action="store_true", help="also write the packaged table (smdm_plugin/data/)")
    a = p.parse_args(argv)
    from smdm_plugin.apps.cli import main as smdm
    from smdm_plugin.metrics.evaluator.model import evaluator_info
    from smdm_plugin.metrics.evaluator.seeds import SeedRow, SeedTable, recipe_of, save_seed_table

    rows, settings, reps = [], None, 0
    for k in a.seeds:
        edir = os.path.join(a.out, f"seed{k}")
        if not os.path.isfile(os.path.join(edir, "evaluator.json")):
            resume = ["--resume"] if os.path.isfile(os.path.join(edir, "train_state.pt")) else []
            cmd = ["evaluator", "train", "--data", a.data, "--out", edir, "--seed", str(k), "--threads",
                   str(a.threads), "--no-progress", *resume, *extra]
            print("smdm " + " ".join(cmd), flush=True)
            if smdm(cmd) != 0:
                print(f"evaluator_seeds.py: error: seed {k}: smdm evaluator train failed (see above)", file=sys.stderr)
                return 2
        info = evaluator_info(edir)
        check = info.get("retrieval_check")
        if not check:
            print(f"evaluator_seeds.py: error: {edir}/evaluator.json has no retrieval_check (trained by an "
                  "smdm-plugin older than 0.8?); delete the folder to retrain it", file=sys.stderr)
            return 2
        s = recipe_of(info["train_settings"])
        if settings is not None and s != settings:
            print(f"evaluator_seeds.py: error: {edir} was trained with other settings than the seeds before it",
                  file=sys.stderr)
            return 2
        settings, reps = s, check["replications"]
        test = info["metrics"]["test"]
        rows.append(SeedRow(k, test["top1"], test["top3"], {c: v for c, v in check.items() if c != "split"},
                            info["best_epoch"], info["train_seconds"]))
    table = SeedTable(os.path.basename(os.path.normpath(a.data)), settings, reps, rows)
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "seeds.json"), "w", encoding="utf-8") as f:
        json.dump(table.to_dict(), f, indent=1)
    if a.save:
        print(f"wrote {save_seed_table(table)}")
    print(table.markdown() + "\n\n" + table.spread_markdown())
    blind = [r.seed for r in rows if not (r.sees_order() and r.sees_captions())]
    if blind:
        print(f"evaluator_seeds.py: R-precision does not fall clearly on seed(s) {blind}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
