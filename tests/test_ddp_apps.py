"""``smdm demo`` and ``smdm ablate`` under ``torchrun --nproc_per_node 2`` (2 gloo processes, CPU):
they train through the one in-package Trainer with DDP, and only rank 0 writes and prints."""
from __future__ import annotations

import json

import numpy as np
import torch

from test_ablate import GRID
from test_trainer_ddp import _torchrun  # the 2-process launcher of the `smdm train` DDP tests

#: test_ablate's grid without its third variant
TINY_GRID = GRID.replace("  - {name: uniform, sparse: {selector: uniform}}\n", "")


def test_demo_under_torchrun_trains_with_ddp_and_writes_one_output_set(tmp_path):
    out = tmp_path / "demo"
    p = _torchrun("-m", "smdm_plugin", "demo", "--quick", "--no-gif", "--batch", "2", "--out", str(out))
    log = p.stdout
    # rank 0 alone prints the tables (each once) ...
    assert log.count("## Training dense vs. sparse") == 1 and log.count("| vw |") == 1, log[-3000:]
    assert log.count("| motion capture (") == 1 and "2 processes x 2" in log
    # ... and writes one output set: the two models trained 3 DDP steps on a global batch of 4
    s = json.loads((out / "summary.json").read_text())
    assert s["training"]["world_size"] == 2 and s["training"]["global_batch"] == 4
    assert s["training"]["dense"]["steps"] == 3 and s["training"]["sparse"]["steps"] == 3
    assert sorted(f.name for f in out.iterdir() if f.name != ".smdm-manifest.json") == sorted(
        ["dense", "sparse", "keyframes.md", "keyframes.csv", "keyframes.png", "training.md", "loss.png",
         "inbetween.md", "summary.json", "evaluator"])
    # rank 0 alone trained the FID evaluator (once) and scored the samples with it
    assert log.count("## Evaluator (FID)") == 1 and np.isfinite(s["training"]["quality"]["dense"]["fid"])
    from smdm_plugin.training.bundle import load_bundle

    assert load_bundle(str(out / "sparse")).sparse and not load_bundle(str(out / "dense")).sparse
def test_ablate_under_torchrun_trains_with_ddp_and_only_rank_zero_reports(hml_dir, tmp_path):
    grid = tmp_path / "grid.yaml"
    grid.write_text(TINY_GRID)
    out = tmp_path / "abl"
    p = _torchrun("-m", "smdm_plugin", "ablate", "--config", str(grid), "--out", str(out), "--data", str(hml_dir),
                  "--no-progress")
    assert p.stdout.count("| dense | ok |") == 1 and p.stdout.count("| sparse (VW) | ok |") == 1, p.stdout[-3000:]
    assert "2 processes (DDP" in p.stdout
    for v in ("dense", "sparse-vw"):
        res = json.loads((out / v / "result.json").read_text())
        assert res["world_size"] == 2 and len(res["losses"]) == 2 and res["status"] == "ok"
        assert res["max_divergence"] == 0.0  # the ranks hold identical weights after training
        assert torch.isfinite(torch.tensor([res["jitter"], res["foot_skating"]])).all()
    from smdm_plugin.apps.ablate import MANIFEST

    assert sorted(f.name for f in out.iterdir() if f.name != ".smdm-manifest.json") == sorted(
        ["dense", "sparse-vw", "config.yaml", "results.md", "results.csv", "loss_curves.png", MANIFEST])
