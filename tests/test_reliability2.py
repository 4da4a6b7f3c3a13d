"""Reliability II: nothing lost under faults (locks, outputs apart from inputs, folders swapped in as
one unit, OS errors as one line), no silent wrong result (loads and inputs validated), resumable
training (kill -9, then --resume: bit-identical to an uninterrupted run)."""
from __future__ import annotations

import errno
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from smdm_plugin.apps import cli
from smdm_plugin.apps import train as train_cli
from smdm_plugin.training import trainer as T
from smdm_plugin.training.data import MotionData
from smdm_plugin.adapters.surgery import as_config
from smdm_plugin.core.config import SparseConfig
from smdm_plugin.core.values import ConfigTypeError
from smdm_plugin.io.outdir import MANIFEST, OutputDir, OutputLock, OutputLockedError, OutputOverlapError, lock_path
from synthetic_data import write_humanml3d

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--latent-dim", "16", "--layers", "1", "--heads", "2", "--ff-size", "32", "--batch", "2",
        "--diffusion-steps", "10", "--no-progress", "--threads", "1"]


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
            "OMP_NUM_THREADS": "1"}


def _smdm(*args, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "smdm_plugin", *map(str, args)], capture_output=True, text=True,
                          env=_env(), timeout=300, **kw)


def _snapshot(folder: Path) -> dict:
    """Every file under ``folder`` -> sha256 of its bytes."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _train(data: Path, out: Path, *extra) -> int:
    return train_cli.main(["--data", str(data), "--out", str(out), "--min-frames", "20", *TINY, *extra])


@pytest.fixture
def data(tmp_path) -> Path:
    return write_humanml3d(tmp_path / "data")


# ------------------------------------------------------------------------------ one writer per folder
def test_second_writer_is_refused_naming_folder_and_owner(tmp_path, data):
    out = tmp_path / "run"
    assert _train(data, out, "--steps", "2") == 0
    before = _snapshot(out)
    with OutputLock(out, "smdm test-holder"):  # a live run (this process) holds the folder
        p = _smdm("train", "--data", data, "--out", out, "--overwrite", "--steps", "1", *TINY)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    line = p.stderr.strip()
    assert len(line.splitlines()) == 1 and "is being written by smdm test-holder" in line
    assert f"pid {os.getpid()}" in line and "run" in line
    assert _snapshot(out) == before and not os.path.exists(lock_path(out))


def test_stale_lock_is_reported_never_taken_over(tmp_path, data):
    out = tmp_path / "run"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    Path(lock_path(out)).write_text(json.dumps({"pid": dead.pid, "host": os.uname().nodename, "command": "smdm demo"}))
    assert _train(data, out, "--steps", "1") == 2
    assert not out.exists() and os.path.exists(lock_path(out))  # still there: the user decides
    with pytest.raises(OutputLockedError, match=rf"stale lock .* left by smdm demo \(pid {dead.pid}, no longer running\)"
                                                r"; if no other run writes there, remove that file"):
        OutputDir(out).open()


# ------------------------------------------------------------------------------ outputs apart from inputs
@pytest.mark.parametrize("where", ["same", "inside", "contains"])
def test_out_overlapping_data_is_refused_before_anything_is_written(tmp_path, data, where, capsys):
    out = {"same": data, "inside": data / "run", "contains": tmp_path}[where]
    before = _snapshot(tmp_path)
    for extra in ([], ["--overwrite"]):
        assert _train(data, out, "--steps", "1", *extra) == 2
        err = capsys.readouterr().err
        assert "pick an output folder apart from the inputs" in err and "--data" in err
    assert _snapshot(tmp_path) == before and sorted(os.listdir(tmp_path)) == ["data"]


def test_overwrite_replaces_only_the_commands_own_files(tmp_path, data, capsys):
    out = tmp_path / "run"
    assert _train(data, out, "--sparse", "--steps", "2") == 0
    manifest = json.loads((out / MANIFEST).read_text())
    assert "sparse_config.json" in manifest["entries"] and "model000000002.pt" in manifest["entries"]
    (out / "notes.txt").write_text("mine")
    (out / "mine").mkdir()
    (out / "mine" / "a.bin").write_bytes(b"\x00\x01")
    assert _train(data, out, "--overwrite", "--steps", "1") == 0  # dense now
    assert (out / "notes.txt").read_text() == "mine" and (out / "mine" / "a.bin").read_bytes() == b"\x00\x01"
    assert not (out / "sparse_config.json").exists() and not (out / "model000000002.pt").exists()
    # a file the command would write, but did not write there: refused up front, nothing changes
    (out / MANIFEST).unlink()
    before = _snapshot(out)
    assert _train(data, out, "--overwrite", "--steps", "1") == 2
    assert "which this command writes but did not write there" in capsys.readouterr().err
    assert _snapshot(out) == before


# ------------------------------------------------------------------------------ one unit; OS errors
def test_failed_overwrite_is_one_line_and_blocks_nothing(tmp_path, data, monkeypatch, capsys):
    """smdm train writes in --out itself (each file atomic; docs/reliability.md): a failed write is one
    line naming the file, leaves no lock, and the next run goes ahead."""
    out = tmp_path / "run"
    assert _train(data, out, "--sparse", "--steps", "2") == 0
    real_save = np.save

    def full_disk(f, *a, **k):  # the disk fills while the new model folder is written (a write names no file)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(np, "save", full_disk)
    rc = cli.main(["train", "--data", str(data), "--out", str(out), "--overwrite", "--steps", "1", "--min-frames",
                   "20", *TINY])
    monkeypatch.setattr(np, "save", real_save)
    err = capsys.readouterr().err
    assert rc == 1 and "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("smdm train: error: ") and last.endswith("Mean.npy: No space left on device")
    assert str(out / "Mean.npy") in last  # the path written
    assert not os.path.exists(lock_path(out)) and not [n for n in os.listdir(out) if n.endswith(".tmp")]
    assert _train(data, out, "--overwrite", "--sparse", "--steps", "2") == 0
    model, config = T.load_trained(str(out))
    assert config is not None


def test_permission_denied_on_the_output_is_one_line(tmp_path, data, monkeypatch, capsys):
    """Tests run as root (chmod does not stop root): the refusal is injected where the folder is made."""
    real = os.makedirs

    def denied(path, *a, **k):
        if os.path.basename(str(path)) == "run":
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(os, "makedirs", denied)
    rc = cli.main(["train", "--data", str(data), "--out", str(tmp_path / "run"), "--steps", "1", "--min-frames", "20",
                   *TINY])
    err = capsys.readouterr().err
    assert rc == 2 and "Permission denied" in err and str(tmp_path / "run") in err and "Traceback" not in err
    assert not (tmp_path / "run").exists() and not os.path.exists(lock_path(tmp_path / "run"))


def test_output_dir_swaps_in_one_unit(tmp_path):
    out = tmp_path / "res"
    with OutputDir(out, command="t") as od:
        Path(od.path, "a.txt").write_text("1")
        assert not out.exists()  # nothing visible until the block ends
    assert (out / "a.txt").read_text() == "1"
    with pytest.raises(RuntimeError):
        with OutputDir(out, overwrite=True, command="t") as od:
            Path(od.path, "a.txt").write_text("2")
            Path(od.path, "b.txt").write_text("2")
            raise RuntimeError("killed half-way")
    assert sorted(os.listdir(out)) == [MANIFEST, "a.txt"] and (out / "a.txt").read_text() == "1"
    assert sorted(os.listdir(tmp_path)) == ["res"]  # no partial folder, no lock left


# ------------------------------------------------------------------------------ resumable training
def test_resume_after_kill_9_is_bit_identical(tmp_path, data, capsys):
    ref, run = tmp_path / "ref", tmp_path / "run"
    steps = 120
    common = ["--data", data, "--min-frames", "20", "--save-every", "20", "--sparse", *TINY]

    def train(*args) -> int:  # in this process (fast); the run to kill is a child process
        return train_cli.main([*map(str, common), *map(str, args)])

    assert train("--out", ref, "--steps", steps) == 0
    # the same run, killed with SIGKILL once a checkpoint is there, then resumed to the same step
    child = subprocess.Popen([sys.executable, "-m", "smdm_plugin", "train", *map(str, common), "--out", str(run),
                              "--steps", "100000"], env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    state = run / T.TRAIN_STATE_FILENAME  # written in --out as training goes
    deadline = time.time() + 120
    while not state.exists() and child.poll() is None and time.time() < deadline:
        time.sleep(0.002)
    os.kill(child.pid, signal.SIGKILL)
    child.wait()
    assert state.exists()
    killed_at = torch.load(state, weights_only=True)["step"]
    assert 20 <= killed_at < steps
    T.load_trained(str(run), step=killed_at)  # the killed run's checkpoint: visible and loadable
    capsys.readouterr()
    # the killed run's lock is reported as stale, never taken over: the user removes it
    assert train("--out", run, "--steps", steps, "--resume") == 2
    assert f"stale lock {lock_path(run)} left by smdm train (pid {child.pid}" in capsys.readouterr().err
    os.unlink(lock_path(run))
    assert train("--out", run, "--steps", steps) == 2  # without --resume: refused, nothing lost
    assert "pass --resume to continue it" in capsys.readouterr().err and state.exists()
    assert train("--out", run, "--steps", steps, "--resume") == 0
    assert f"resumed at step {killed_at}" in capsys.readouterr().out
    a = torch.load(ref / f"model{steps:09d}.pt", weights_only=True)
    b = torch.load(run / f"model{steps:09d}.pt", weights_only=True)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert (ref / "losses.csv").read_text() == (run / "losses.csv").read_text()
    # a finished run continues to more steps the same way; its earlier checkpoints stay
    assert train("--out", run, "--steps", steps + 20, "--resume") == 0
    assert (run / f"model{steps + 20:09d}.pt").exists() and (run / f"model{steps:09d}.pt").exists()
    # other settings: refused, naming what differs, the folder unchanged
    before = _snapshot(run)
    assert train("--out", run, "--steps", steps + 40, "--resume", "--lr", "0.001") == 2
    assert "lr: saved 0.0002, now 0.001" in capsys.readouterr().err and _snapshot(run) == before
    assert sorted(os.listdir(tmp_path)) == ["data", "ref", "run"]  # no partial folder, no lock left


# ------------------------------------------------------------------------------ loads validate
@pytest.fixture
def model_dir(tmp_path, data) -> Path:
    out = tmp_path / "m"
    assert _train(data, out, "--sparse", "--steps", "1") == 0
    return out


@pytest.mark.parametrize("edit,match", [
    (lambda d: (d / "model000000001.pt").write_bytes(b""), r"model000000001.pt: empty checkpoint file"),
    (lambda d: (d / "model000000001.pt").write_bytes((d / "model000000001.pt").read_bytes()[:300]),
     r"model000000001.pt: not a readable checkpoint \(truncated or corrupt"),
    (lambda d: (d / "args.json").write_bytes(b'{"sparse": true, "sparse_reduction": "\xff"}'),
     r"args.json: not UTF-8 text"),
    (lambda d: (d / "sparse_config.json").write_bytes(b"\xff\xfe{}"), r"sparse_config.json: not UTF-8"),
    (lambda d: (d / "sparse_config.json").write_text('{"reduction": 0.8}'),
     r"sparse_config.json: missing field\(s\) enabled, selector"),
    (lambda d: (d / "args.json").write_text('{"sparse": true, "sparse_reduction": 0.5}'),
     r"args.json and .*sparse_config.json disagree: reduction: args.json 0.5, sparse_config.json 0.8"),
    (lambda d: _edit_json(d / "train_config.json", diffusion_steps=0), r"train_config.json: diffusion_steps=0: expected an integer >= 1"),
    (lambda d: _edit_json(d / "train_config.json", diffusion_steps=-5), r"diffusion_steps=-5"),
    (lambda d: _edit_json(d / "train_config.json", steps="many"), r"train_config.json: steps='many'"),
    (lambda d: np.save(d / "Std.npy", np.r_[np.nan, np.ones(262)].astype(np.float32)), r"Std.npy: std holds a non-finite"),
    (lambda d: np.save(d / "Std.npy", np.ones(10, np.float32)), r"Std.npy: std must have shape \[263\], got \[10\]"),
    (lambda d: np.save(d / "Std.npy", np.zeros(263, np.float32)), r"Std.npy: std must be > 0 everywhere"),
    (lambda d: np.save(d / "Mean.npy", np.ones(263, np.complex64)), r"Mean.npy: mean must be real numbers"),
    (lambda d: _edit_json(d / "backbone.json", njoints=0), r"backbone.json: njoints=0"),
])
def test_loads_validate_what_they_read(model_dir, edit, match):
    edit(model_dir)
    with pytest.raises(ValueError, match=match) as e:
        T.load_trained(str(model_dir))
    assert "\n" not in str(e.value)


def test_nonfinite_weights_are_refused(model_dir):
    sd = torch.load(model_dir / "model000000001.pt", weights_only=True)
    k = next(k for k, v in sd.items() if v.is_floating_point())
    sd[k] = sd[k].clone().fill_(float("nan"))
    torch.save(sd, model_dir / "model000000001.pt")
    with pytest.raises(ValueError, match=rf"tensor {k} holds non-finite values"):
        T.load_trained(str(model_dir))


def _edit_json(path: Path, **changes) -> None:
    path.write_text(json.dumps({**json.loads(path.read_text()), **changes}))


def test_bundle_motion_json_is_validated(tmp_path):
    from smdm_plugin.training.bundle import load_bundle, save_bundle
    from smdm_plugin.io.representation import Representation
    from smdm_plugin.reference.backbone import TinyMDM
    from smdm_plugin.reference.diffusion import SimpleDiffusion

    rep = Representation("joints66")
    kw = dict(njoints=66, nfeats=1, latent_dim=16, ff_size=32, num_layers=1, num_heads=2, cond_mode="no_cond")
    d = save_bundle(str(tmp_path / "b"), TinyMDM(**kw), SimpleDiffusion(10), kw, rep, np.zeros(66), np.ones(66))
    load_bundle(d)
    for change, match in ((dict(fps=0), r"motion.json: fps=0: expected a finite number > 0"),
                          (dict(diffusion_steps=0), r"diffusion_steps=0: expected an integer >= 1"),
                          (dict(std=[1.0] * 65), r"std must have shape \[66\]"),
                          (dict(mean=[float("nan")] + [0.0] * 65), r"mean holds a non-finite")):
        text = (tmp_path / "b" / "motion.json").read_text()
        _edit_json(tmp_path / "b" / "motion.json", **change)
        with pytest.raises(ValueError, match=match):
            load_bundle(d)
        (tmp_path / "b" / "motion.json").write_text(text)
    meta = json.loads((tmp_path / "b" / "motion.json").read_text())
    del meta["fps"]
    (tmp_path / "b" / "motion.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"motion.json: missing field\(s\) fps"):
        load_bundle(d)


# ------------------------------------------------------------------------------ input data before step 0
@pytest.mark.parametrize("edit,match", [
    (lambda d: np.save(d / "new_joint_vecs" / "train001.npy", np.full((52, 263), np.nan, np.float32)),
     r"train001.npy: motion holds a non-finite value"),
    (lambda d: np.save(d / "new_joint_vecs" / "train001.npy", np.zeros((52, 250), np.float32)),
     r"train001.npy: motion must have shape \[\*, 263\], got \[52, 250\]"),
    (lambda d: np.save(d / "new_joint_vecs" / "train001.npy", np.zeros((52, 263), np.complex64)),
     r"train001.npy: motion must be real numbers"),
    (lambda d: ((d / "new_joint_vecs" / "train001.npy").unlink(), (d / "new_joint_vecs" / "train001.npy").mkdir()),
     r"train001.npy: is a folder, expected a .npy file"),
    (lambda d: np.save(d / "Std.npy", np.ones(200, np.float32)), r"Std.npy: std must have shape \[263\]"),
    (lambda d: np.save(d / "Std.npy", np.r_[0.0, np.ones(262)].astype(np.float32)), r"Std.npy: std must be > 0"),
    (lambda d: np.save(d / "Mean.npy", np.r_[np.inf, np.ones(262)].astype(np.float32)), r"Mean.npy: mean holds a non-finite"),
    (lambda d: (d / "train.txt").write_bytes(b"\xff\xfe\x00"), r"train.txt: not UTF-8"),
])
def test_bad_training_data_is_one_line_before_step_0(tmp_path, data, edit, match, capsys):
    edit(data)
    assert _train(data, tmp_path / "run", "--steps", "1") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("smdm train: data: ")
    import re

    assert re.search(match, err), err
    assert not (tmp_path / "run").exists()


def test_clips_too_short_for_the_reduction(tmp_path, capsys):
    data = write_humanml3d(tmp_path / "d", train=(6, 40), val=(40,))
    assert _train(data, tmp_path / "run", "--min-frames", "2", "--sparse", "--steps", "1") == 2
    err = capsys.readouterr().err
    assert "train000.npy has 6 frames: at reduction 0.8 it would keep 2" in err and "--min-frames 8" in err
    assert _train(data, tmp_path / "run", "--min-frames", "8", "--sparse", "--steps", "1") == 0


# ------------------------------------------------------------------------------ numbers and configs
def test_numpy_scalars_are_numbers_and_dicts_are_configs():
    from smdm_plugin.core.selection import keyframe_count, select_keyframes  # noqa: F401

    c = SparseConfig(reduction=np.float32(0.8), gamma=np.float64(0.1), fsq=np.bool_(False),
                     diffusion_steps=np.int64(50), fsq_levels=np.array([8, 5]), mask_noise=np.array(0.1))
    assert c == SparseConfig(reduction=0.8, gamma=0.1, fsq=False, diffusion_steps=50, fsq_levels=(8, 5), mask_noise=0.1)
    assert type(c.reduction) is float and type(c.fsq) is bool and type(c.diffusion_steps) is int
    with pytest.raises(ConfigTypeError, match="reduction"):
        SparseConfig(reduction=np.complex64(0.5))
    with pytest.raises(ConfigTypeError, match="diffusion_steps"):
        SparseConfig(diffusion_steps=np.float32(50))
    # the one conversion of what users pass as a config (sparsify's)
    assert as_config({"reduction": 0.7}) == SparseConfig(reduction=0.7)
    assert as_config(c) is c and as_config(None) == SparseConfig()
    with pytest.raises(ValueError, match=r"unknown option 'redution'; did you mean 'reduction'"):
        as_config({"redution": 0.7})
    with pytest.raises(TypeError, match=r"sparsify: config must be a SparseConfig, a dict of its fields or None"):
        as_config([("reduction", 0.7)])
    from smdm_plugin.core.selection import _check_reduction
    from smdm_plugin.metrics.quality import _fps

    assert _check_reduction(np.float32(0.8), "f") == 0.8 and _fps("f", np.float32(20)) == 20.0


def test_ablate_variant_resumes_with_the_trainers_mechanism(tmp_path):
    """smdm ablate --resume continues an interrupted variant from its checkpoint (the trainer's
    state, as smdm train --resume) instead of starting over, with the same result."""
    from smdm_plugin.apps import ablate
    from smdm_plugin.apps.ablate import grid

    cfg = grid.load_config(str(ROOT / "configs" / "ablations" / "quick.yaml"))
    cfg.update(steps=20, batch=2, model={**cfg["model"], "latent_dim": 16, "ff_size": 32, "num_layers": 1})
    cfg["eval"] = {**cfg["eval"], "samples": 2, "frames": 40}
    data = MotionData(str(write_humanml3d(tmp_path / "d", train=(60, 52, 48, 70), val=(44, 56))), 60, 40)
    variant = next(v for v in cfg["variants"] if v["name"] == "sparse (VW)")
    dev = torch.device("cpu")
    straight = ablate.run_variant(cfg, variant, data, dev)
    ckpt = tmp_path / "ckpt"
    real_step, calls = T.Trainer.step, []

    def interrupted(self):
        if self.step_count == 13:  # after the checkpoint at step 12 (every 2 steps)
            raise KeyboardInterrupt
        calls.append(self.step_count)
        return real_step(self)

    T.Trainer.step = interrupted
    try:
        with pytest.raises(KeyboardInterrupt):
            ablate.run_variant(cfg, variant, data, dev, checkpoint_dir=str(ckpt))
    finally:
        T.Trainer.step = real_step
    assert torch.load(ckpt / T.TRAIN_STATE_FILENAME, weights_only=True)["step"] == 12
    resumed = ablate.run_variant(cfg, variant, data, dev, checkpoint_dir=str(ckpt))
    assert resumed["resumed_at"] == 12 and straight["resumed_at"] == 0
    assert resumed["losses"] == straight["losses"] and resumed["val_loss"] == straight["val_loss"]
    assert resumed["ees"] == straight["ees"]


def test_resume_without_a_run_is_refused_and_leaves_nothing(tmp_path, data, capsys):
    assert _train(data, tmp_path / "o", "--steps", "1", "--resume") == 2
    assert "holds no run to continue" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == ["data"]


def test_ctrl_c_keeps_the_checkpoint_for_resume(tmp_path, data, monkeypatch, capsys):
    real_step = T.Trainer.step

    def step(self):
        if self.step_count == 3:
            raise KeyboardInterrupt
        return real_step(self)

    monkeypatch.setattr(T.Trainer, "step", step)
    rc = cli.main(["train", "--data", str(data), "--out", str(tmp_path / "o"), "--steps", "9", "--save-every", "2",
                   "--min-frames", "20", *TINY])
    assert rc == 130 and "rerun with --resume to continue from step 2" in capsys.readouterr().err
    assert (tmp_path / "o" / "model000000002.pt").exists() and not (tmp_path / ".o.partial").exists()
    assert not os.path.exists(lock_path(tmp_path / "o"))
    monkeypatch.setattr(T.Trainer, "step", real_step)
    assert _train(data, tmp_path / "o", "--steps", "9", "--save-every", "2", "--resume") == 0
    assert (tmp_path / "o" / "model000000009.pt").exists() and not (tmp_path / ".o.partial").exists()


def test_options_files_must_agree_with_the_saved_config(model_dir, tmp_path):
    import argparse

    from smdm_plugin.integrations.motiondiffuse import config_from_opt

    # diffusion_steps is set from the diffusion when the model is built: a CLI default there is fine
    (model_dir / "args.json").write_text('{"sparse": true, "sparse_diffusion_steps": 50, "sparse_reduction": 0.8}')
    T.load_trained(str(model_dir))
    # MotionDiffuse: opt.txt's sparse_* options (strings, as get_opt reads them) vs sparse_config.json
    (tmp_path / "model").mkdir()
    SparseConfig(reduction=0.7).save(tmp_path / "model")
    opt = argparse.Namespace(is_train=False, model_dir=str(tmp_path / "model"), sparse="True", sparse_reduction="0.7",
                             sparse_diffusion_steps="50")
    assert config_from_opt(opt).reduction == 0.7
    opt.sparse_reduction = "0.5"
    with pytest.raises(ValueError, match=r"opt.txt and .*sparse_config.json disagree: reduction: opt.txt 0.5, "
                                         r"sparse_config.json 0.7"):
        config_from_opt(opt)
