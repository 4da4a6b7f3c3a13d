"""``torchrun --nproc_per_node 2 -m smdm_plugin train`` (2 gloo processes, CPU) on real clips.

After k steps both ranks hold identical parameters, only rank 0 wrote files, and the result
matches one process trained on the concatenated batch (2 x 4 samples): t and noise are a function
of (seed, step, global sample index), dropout and mask noise are 0, so the single process is the
exact reference up to float rounding in the batched matmuls.
"""
from __future__ import annotations

import json
import os
import shutil
import re
import subprocess
import sys

import pytest
import torch

pytest.importorskip("torch.distributed")
if not torch.distributed.is_available() or not torch.distributed.is_gloo_available():
    pytest.skip("torch.distributed with gloo is not available", allow_module_level=True)

from helpers.commands import torchrun as _torchrun
from helpers.paths import ROOT as REPO, TESTS

WORKER = TESTS / "helpers" / "ddp_worker.py"
STEPS = 4
TINY = ["--latent-dim", "64", "--layers", "2", "--heads", "4", "--ff-size", "128", "--dropout", "0",
        "--diffusion-steps", "20", "--lr", "1e-3", "--steps", str(STEPS), "--seed", "7", "--no-progress"]
SPARSE = ["--sparse", "--sparse_mask_noise", "0"]


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["OMP_NUM_THREADS"] = "1"
    return env


@pytest.fixture(scope="module")
def runs(hml_dir, tmp_path_factory):
    """The 2-process run (instrumented worker) and the single-process reference."""
    base = tmp_path_factory.mktemp("ddp")
    dump = base / "dump"
    dump.mkdir()
    ddp_out, single_out = base / "ddp", base / "single"
    proc = _torchrun(str(WORKER), str(dump), "--", "--data", str(hml_dir), "--out", str(ddp_out),
                     "--batch", "4", *TINY, *SPARSE)
    from smdm_plugin.apps.train import main

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the workers (OMP_NUM_THREADS=1)
    try:
        assert main(["--data", str(hml_dir), "--out", str(single_out), "--batch", "8", *TINY, *SPARSE]) == 0
    finally:
        torch.set_num_threads(threads)
    return {"dump": dump, "ddp": ddp_out, "single": single_out, "log": proc.stdout + proc.stderr}


def _load(path):
    return torch.load(path, map_location="cpu", weights_only=True)


def test_ranks_hold_identical_parameters(runs):
    r0, r1 = _load(runs["dump"] / "rank0.pt"), _load(runs["dump"] / "rank1.pt")
    assert sorted(r0) == sorted(r1)
    for k in r0:
        assert torch.equal(r0[k], r1[k]), k
    ckpt = _load(runs["ddp"] / f"model{STEPS:09d}.pt")
    assert sorted(ckpt) == sorted(r0)
    assert all(torch.equal(ckpt[k], r0[k]) for k in r0)
    result = json.loads((runs["ddp"] / "result.json").read_text())
    assert result["world_size"] == 2 and result["global_batch"] == 8 and result["max_divergence"] == 0.0


def test_only_rank_zero_writes(runs):
    w0 = json.loads((runs["dump"] / "rank0_writes.json").read_text())
    w1 = json.loads((runs["dump"] / "rank1_writes.json").read_text())
    assert w1 == []
    names = {os.path.basename(p) for p in w0}
    assert {f"model{STEPS:09d}.pt", "backbone.json", "sparse_config.json", "train_config.json", "result.json",
            "losses.csv", "loss.png", "Mean.npy", "Std.npy"} <= names
    # written in --out itself as training goes (a long run; docs/reliability.md)
    assert all(os.path.dirname(os.path.abspath(p)) == os.path.abspath(runs["ddp"]) for p in w0)
    assert sorted(os.listdir(runs["ddp"])) == sorted(os.listdir(runs["single"]))


def test_two_processes_match_one_process_on_the_concatenated_batch(runs, hml_dir):
    from smdm_plugin.io.humanml3d import load_humanml3d
    from smdm_plugin.training.data import MotionSet
    from smdm_plugin.training.trainer import TrainConfig, Trainer, load_trained

    ddp = json.loads((runs["ddp"] / "result.json").read_text())
    single = json.loads((runs["single"] / "result.json").read_text())
    assert len(ddp["losses"]) == len(single["losses"]) == STEPS
    assert ddp["losses"] == pytest.approx(single["losses"], rel=1e-5, abs=1e-6)

    a, b = _load(runs["ddp"] / f"model{STEPS:09d}.pt"), _load(runs["single"] / f"model{STEPS:09d}.pt")
    # the initial weights (same seed), to measure the difference against what training moved
    cfg = TrainConfig.from_dict({k: v for k, v in json.loads((runs["single"] / "train_config.json").read_text()).items()
                                 if k in TrainConfig.__dataclass_fields__})
    init = Trainer(cfg, MotionSet.from_split(load_humanml3d(str(hml_dir))), device="cpu").model.state_dict()
    diff = torch.cat([(a[k].float() - b[k].float()).reshape(-1) for k in a if a[k].is_floating_point()])
    moved = torch.cat([(b[k].float() - init[k].float()).reshape(-1) for k in b if b[k].is_floating_point()])
    print(f"|ddp - single| max {diff.abs().max():.3g}, norm ratio {diff.norm() / moved.norm():.3g}")
    assert float(moved.norm()) > 0.1  # training did move the weights
    assert float(diff.norm() / moved.norm()) < 1e-3
    assert float(diff.abs().max()) < 1e-4

    # the checkpoint folder reloads into an equal sparse model
    model, config = load_trained(str(runs["ddp"]))
    assert config is not None and config.enabled and config.mask_noise == 0.0
    assert all(torch.equal(model.state_dict()[k], a[k]) for k in a)


def test_refuses_existing_output_on_every_rank(runs, hml_dir):
    proc = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
         "-m", "smdm_plugin", "train", "--data", str(hml_dir), "--out", str(runs["ddp"]), *TINY],
        cwd=str(REPO), env=_env(), capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0
    assert proc.stderr.count("holds a run of smdm train (interrupted or finished); pass --resume to continue it, "
                             "--overwrite to start over") == 1  # rank 0 says it, once
    # both ranks stop: each exits 2, unless torchrun ends the second one first (SIGTERM, -15) once the
    # first has exited; which happens first depends on the machine's load
    codes = re.findall(r"exitcode\s*:\s*(-?\d+)", proc.stderr)
    assert "2" in codes and set(codes) <= {"2", "-15"}, proc.stderr[-2000:]
    assert "smdm_plugin/" not in proc.stderr  # no traceback from the workers
    assert (runs["ddp"] / f"model{STEPS:09d}.pt").exists()


def test_resume_under_torchrun_equals_the_uninterrupted_run(runs, hml_dir, tmp_path):
    """``--resume`` of the 2-process run (every rank's random streams restored) continues it to
    the same weights as a 2-process run of all the steps at once."""
    i = TINY.index("--steps") + 1
    more = ["--batch", "4", *TINY[:i], str(STEPS + 2), *TINY[i + 1:]]  # as the runs fixture
    run, ref = tmp_path / "run", tmp_path / "ref"
    shutil.copytree(runs["ddp"], run)
    p = _torchrun("-m", "smdm_plugin", "train", "--data", str(hml_dir), "--out", str(run), "--resume", *more, *SPARSE)
    assert p.stdout.count(f"resumed at step {STEPS}") == 1
    _torchrun("-m", "smdm_plugin", "train", "--data", str(hml_dir), "--out", str(ref), *more, *SPARSE)
    a, b = _load(run / f"model{STEPS + 2:09d}.pt"), _load(ref / f"model{STEPS + 2:09d}.pt")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert (run / "losses.csv").read_text() == (ref / "losses.csv").read_text()
