"""Why a generator can score a lower FID than the real train motions: the FID of real motion sets
against the evaluation motions of a study, with one thing changed at a time (95% bootstrap intervals).

    python scripts/fid_anchors.py results/preregistered_t50            # a study folder (its config and cached evaluator)

Rows: the evaluation motions against a second draw of themselves (the floor); the validation motions
(motions the evaluator never trained on) against them, and as many train motions drawn at random
(same count: what the evaluator having trained on the train motions does); as many train motions as
evaluation motions; every train motion; the train motions with the evaluation captions and lengths
(:func:`smdm_plugin.apps.ablate.study.matched_train`: what a generator that reproduces its training
motions would score), and with the evaluation lengths only (a random train motion long enough, cut
to each length). Beside them the evaluator's R-precision top-3 on the train and the evaluation
motions (a train R-precision far above the evaluation one: the evaluator knows its training motions).
Writes ``DIR/fid_anchors.json`` and prints a markdown table. The study's evaluator is read from its
cache in ``DIR/evaluator/``, or trained there first as the study would (minutes), e.g. for a study
whose evaluator was not committed: the weights are the study's when the training is deterministic
(compare ``evaluator.pt`` with the hash the study recorded, docs/decisive/EVALUATOR.sha256).

Exit status: 0, or 2 when the folder is not a study's results (one line naming what was expected).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any, Dict, List, Optional, Sequence


def measure(folder: str, resamples: int = 200) -> Dict[str, Any]:
    """The rows of the table (see the module docstring) for the study in ``folder``."""
    import numpy as np
    import torch
    import yaml

    from smdm_plugin.apps.ablate import study
    from smdm_plugin.metrics.evaluator.data import load_captioned
    from smdm_plugin.metrics.evaluator.train import held_out_accuracy
    from smdm_plugin.metrics.t2m import fid_bootstrap, frechet_distance

    with open(os.path.join(folder, "config.yaml"), encoding="utf-8") as f:
        cfg = study.resolve_study(yaml.safe_load(f))
    data = study.StudyData(cfg["data"], cfg)
    evaluator, key, edir = study.build_evaluator(cfg, data, folder, log=print)
    real = evaluator.embed_motion(data.raw, data.lengths).double().numpy()
    anchors = study.fid_anchors(evaluator, data, real, cfg["text"])
    train_x, train_L = data.train.padded()
    std, mean = torch.from_numpy(data.std), torch.from_numpy(data.mean)
    train = evaluator.embed_motion(train_x * std + mean, train_L).double().numpy()
    val = load_captioned(cfg["data"], "val")
    N = cfg["max_frames"]
    vx = np.zeros((len(val), N, data.raw.shape[-1]), np.float32)
    vL = []
    for i, m in enumerate(val.motions):
        vx[i, :min(len(m), N)] = m[:N]
        vL.append(min(len(m), N))
    val_emb = evaluator.embed_motion(torch.from_numpy(vx), torch.tensor(vL)).double().numpy()
    rng = np.random.default_rng(5)
    same_n = [frechet_distance(train[rng.choice(len(train), len(val_emb), replace=False)], real)
              for _ in range(resamples)]
    v = fid_bootstrap(val_emb, real, resamples, seed=6)
    # the evaluation lengths alone: for each evaluation motion a random train motion at least as long, cut to it
    long_enough = [[j for j in range(len(train_L)) if int(train_L[j]) >= L] or [int(np.argmax(train_L))]
                   for L in data.lengths.tolist()]
    by_len = []
    for _ in range(resamples // 4):
        idx = [int(rng.choice(c)) for c in long_enough]
        lens = torch.minimum(data.lengths, train_L[idx])
        by_len.append(frechet_distance(evaluator.embed_motion(train_x[idx] * std + mean, lens).double().numpy(), real))
    rows = [("real evaluation motions against a second draw of themselves (floor)", anchors["fid_floor"],
             anchors["fid_floor_interval"], len(real)),
            ("validation motions (never trained on)", v.fid, [v.low, v.high], len(val_emb)),
            (f"{len(val_emb)} train motions drawn at random (trained on)", float(np.mean(same_n)),
             [float(np.percentile(same_n, 2.5)), float(np.percentile(same_n, 97.5))], len(val_emb)),
            (f"{len(real)} train motions drawn at random", anchors["fid_train_sample"],
             anchors["fid_train_sample_interval"], len(real)),
            ("every train motion", anchors["fid_train_vs_eval"], anchors["fid_train_vs_eval_interval"], len(train)),
            ("train motions with the evaluation lengths (random captions)", float(np.mean(by_len)),
             [float(np.percentile(by_len, 2.5)), float(np.percentile(by_len, 97.5))], len(real)),
            ("train motions with the evaluation captions and lengths", anchors["fid_train_matched"],
             anchors["fid_train_matched_interval"], len(real))]
    ev = evaluator.ev
    acc = {s: held_out_accuracy(ev, load_captioned(cfg["data"], s), 5, seed=0)["top3"] for s in ("train", "val", "test")}
    return {"folder": folder, "evaluator": edir, "rows": [dict(zip(("set", "fid", "interval", "motions"), r))
                                                          for r in rows], "r_precision_top3": acc}


def markdown(res: Dict[str, Any]) -> List[str]:
    out = ["| motions against the evaluation motions | motions | FID | 95% interval |", "| --- | ---: | ---: | ---: |"]
    out += [f"| {r['set']} | {r['motions']} | {r['fid']:.2f} | [{r['interval'][0]:.2f}, {r['interval'][1]:.2f}] |"
            for r in res["rows"]]
    acc = res["r_precision_top3"]
    out += ["", f"Evaluator R-precision top-3 (pool 32 or all, 5 caption draws): train {acc['train']:.3f}, "
                f"val {acc['val']:.3f}, test {acc['test']:.3f}."]
    return out


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="fid_anchors.py", description=__doc__.splitlines()[0])
    p.add_argument("folder", help="a study's results folder (config.yaml, evaluator/)")
    p.add_argument("--resamples", type=int, default=200, help="bootstrap resamples (default 200)")
    a = p.parse_args(argv)
    if not os.path.isfile(os.path.join(a.folder, "config.yaml")):
        print(f"fid_anchors.py: error: {a.folder}: no config.yaml; expected a study results folder (smdm ablate "
              "--config <study> --out FOLDER)", file=sys.stderr)
        return 2
    import torch

    torch.set_num_threads(1)
    res = measure(a.folder, a.resamples)
    with open(os.path.join(a.folder, "fid_anchors.json"), "w", encoding="utf-8") as f:
        json.dump(res, f, indent=1)
    print("\n".join(markdown(res)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
