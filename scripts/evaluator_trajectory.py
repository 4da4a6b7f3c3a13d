"""How an evaluator's R-precision check moves over its matching epochs: train one seed of a recipe
and, every ``--every`` matching epochs, measure on the test split the check ``smdm evaluator train``
prints at its end (:func:`smdm_plugin.metrics.evaluator.check.retrieval_check`: R-precision top-1 /
top-3, time-reversed and caption-swapped, paired drops, FID floor; ``--replications`` of smdm eval's
protocol) beside the validation loss and validation R-precision the weights can be chosen by.

    python scripts/evaluator_trajectory.py --data ../shared/data/cmu-humanml3d-large --seed 0 --epochs 40
    python scripts/evaluator_trajectory.py --data ... --seed 0 -- '{"reversed_negatives": false, "select": "val_rprec"}'

The optional last argument (after ``--``) is a JSON object of
:class:`~smdm_plugin.metrics.evaluator.train.TrainSettings` fields over ``smdm evaluator train``'s
defaults. One JSON object per measured epoch on stdout (docs/evaluation.md reads the recipe's
trajectories from these). Nothing is written to disk.
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any, Dict, Optional, Sequence


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: Dict[str, Any] = {}
    if "--" in argv:
        i = argv.index("--")
        try:
            extra = json.loads(" ".join(argv[i + 1:]) or "{}")
        except ValueError as e:
            print(f"evaluator_trajectory.py: error: the settings after -- are not a JSON object ({e})", file=sys.stderr)
            return 2
        argv = argv[:i]
    p = argparse.ArgumentParser(prog="evaluator_trajectory.py", description=__doc__.splitlines()[0])
    p.add_argument("--data", required=True, help="HumanML3D-format folder with train / val / test splits")
    p.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    p.add_argument("--epochs", type=int, default=None, help="matching epochs (default: the recipe's)")
    p.add_argument("--every", type=int, default=5, help="measure every this many matching epochs (default 5)")
    p.add_argument("--replications", type=int, default=5, help="replications of the check (default 5)")
    a = p.parse_args(argv)
    import torch

    from smdm_plugin.metrics.evaluator.check import retrieval_check
    from smdm_plugin.metrics.evaluator.data import load_captioned
    from smdm_plugin.metrics.evaluator.train import (DEFAULT_RECIPE, TrainSettings, build_evaluator, held_out_accuracy,
                                                     train_evaluator, validation_loss)

    torch.set_num_threads(1)
    try:
        s = TrainSettings(**{"recipe": DEFAULT_RECIPE, "seed": a.seed, **({"epochs": a.epochs} if a.epochs else {}),
                             **extra})
        train, val, test = (load_captioned(a.data, split) for split in ("train", "val", "test"))
    except (TypeError, ValueError, FileNotFoundError) as e:
        print(f"evaluator_trajectory.py: error: {e}", file=sys.stderr)
        return 2
    ev = build_evaluator(train, s)

    def measure(st: Dict[str, Any]) -> None:
        e = st["epoch"] - s.pretrain_epochs
        if e <= 0 or (e % a.every and e != s.epochs):
            return
        c = retrieval_check(ev, test, replications=a.replications, seed=0)
        acc = held_out_accuracy(ev, val, s.eval_draws, seed=s.seed)
        row = {"epoch": e, "loss": st["history"][-1]["loss"], "val_loss": validation_loss(ev, val, s, s.eval_draws, s.seed),
               "val_top1": acc["top1"], "val_top3": acc["top3"], **c.to_dict(), "seconds": st["seconds"]}
        print(json.dumps(row), flush=True)
        ev.train()
        if s.recipe == "t2m":
            ev.movement_encoder.eval()

    train_evaluator(ev, train, val, s, on_epoch=measure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
