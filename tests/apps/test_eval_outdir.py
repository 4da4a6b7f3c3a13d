"""`smdm eval` and `smdm evaluator train` write their folders as `smdm train` does (io/outdir.py):
one writer per folder (lock naming the owner), `--out` apart from every input (refused before
anything is written, with or without `--overwrite`), `--overwrite` replacing only the command's own
files (manifest), a failure mid-write leaving the earlier results byte-identical (one line, non-zero),
and the evaluator's `--resume` continuing an interrupted run's partial folder exactly."""
from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path
from typing import List

import numpy as np
import pytest
import torch

from smdm_plugin.apps import cli
from smdm_plugin.io.outdir import MANIFEST, OutputLock, lock_path, partial_path

from helpers.commands import snapshot as _snapshot
from helpers.synthetic_data import write_humanml3d

TINY_EV = ["--hidden", "16", "--dim", "8", "--no-progress", "--threads", "1"]


def _train_ev(out: Path, *extra: str) -> int:
    return cli.main(["evaluator", "train", "--out", str(out), "--epochs", "2", *TINY_EV, *extra])


@pytest.fixture(scope="module")
def evaluator(tmp_path_factory) -> Path:
    """A tiny evaluator on the embedded CMU clips (joints66)."""
    out = tmp_path_factory.mktemp("ev") / "ev"
    assert _train_ev(out, "--epochs", "1") == 0
    return out


@pytest.fixture(scope="module")
def motions(tmp_path_factory) -> Path:
    """The embedded test split's own motions, one ``<id>.npy`` each (what ``--motions`` reads)."""
    from smdm_plugin.metrics.evaluator.data import load_split

    test = load_split(None, "test")
    folder = tmp_path_factory.mktemp("m") / "m"
    folder.mkdir()
    for i, m in zip(test.ids, test.motions):
        np.save(folder / f"{i}.npy", m)
    return folder


def _eval_args(evaluator: Path, motions: Path, out: Path) -> List[str]:
    return ["eval", "--evaluator", str(evaluator), "--motions", str(motions), "--out", str(out), "--threads", "1"]


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# ------------------------------------------------------------------------------ one writer per folder
@pytest.mark.parametrize("command", ["eval", "evaluator"])
def test_second_writer_is_refused_naming_folder_and_owner(command, tmp_path, evaluator, motions, capsys):
    out = tmp_path / "res"
    args = _eval_args(evaluator, motions, out) if command == "eval" else \
        ["evaluator", "train", "--out", str(out), "--epochs", "1", *TINY_EV]
    assert cli.main(args) == 0
    before = _snapshot(out)
    capsys.readouterr()
    with OutputLock(out, "smdm test-holder"):  # a live run (this process) holds the folder
        assert cli.main(args + ["--overwrite"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "is being written by smdm test-holder" in line and f"pid {os.getpid()}" in line and "res" in line
    assert _snapshot(out) == before and not os.path.exists(lock_path(out)) and not os.path.exists(partial_path(out))


# ------------------------------------------------------------------------------ outputs apart from inputs
@pytest.mark.parametrize("where", ["same", "inside", "contains"])
def test_out_overlapping_data_is_refused_before_anything_is_written(where, tmp_path, evaluator, motions, capsys):
    data = tmp_path / "data"
    data.mkdir()
    (data / "train.txt").write_text("a\n")
    out = {"same": data, "inside": data / "res", "contains": tmp_path}[where]
    before = _snapshot(tmp_path)
    runs = (["evaluator", "train", "--data", str(data), "--out", str(out), *TINY_EV],
            _eval_args(evaluator, motions, out) + ["--data", str(data)])
    for args in runs:
        for extra in ([], ["--overwrite"]):
            assert cli.main(args + extra) == 2
            line = _one_line(capsys.readouterr().err)
            assert "pick an output folder apart from the inputs" in line and "--data" in line
    # the other inputs of smdm eval too
    for name, path in (("--evaluator", evaluator), ("--motions", motions)):
        assert cli.main(_eval_args(evaluator, motions, path / "res") + ["--overwrite"]) == 2
        assert f"the input {name}" in _one_line(capsys.readouterr().err)
        assert not (path / "res").exists() and not os.path.exists(lock_path(path / "res"))
    assert _snapshot(tmp_path) == before and sorted(os.listdir(tmp_path)) == ["data"]


# ------------------------------------------------------------------------------ --overwrite: own files only
def test_eval_overwrite_replaces_only_its_own_files(tmp_path, evaluator, motions, capsys):
    out = tmp_path / "res"
    assert cli.main(_eval_args(evaluator, motions, out)) == 0
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["command"] == "smdm eval" and manifest["entries"] == ["metrics.json", "metrics.md", "metrics.png"]
    (out / "notes.txt").write_text("mine")
    (out / "metrics.json").write_text("{}")  # the command's own file: replaced
    capsys.readouterr()
    assert cli.main(_eval_args(evaluator, motions, out)) == 2  # not without --overwrite
    assert "--overwrite" in _one_line(capsys.readouterr().err)
    assert cli.main(_eval_args(evaluator, motions, out) + ["--overwrite"]) == 0
    assert (out / "notes.txt").read_text() == "mine" and "fid" in json.loads((out / "metrics.json").read_text())
    assert sorted(os.listdir(tmp_path)) == ["res"]  # no partial folder, no lock left
    # a file the command writes, in a folder no manifest describes: refused up front, nothing changes
    (out / MANIFEST).unlink()
    before = _snapshot(out)
    capsys.readouterr()
    assert cli.main(_eval_args(evaluator, motions, out) + ["--overwrite"]) == 2
    assert "which this command writes but did not write there" in _one_line(capsys.readouterr().err)
    assert _snapshot(out) == before


def test_evaluator_overwrite_replaces_only_its_own_files(tmp_path):
    out = tmp_path / "ev"
    assert _train_ev(out, "--epochs", "1") == 0
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["command"] == "smdm evaluator train"
    assert sorted(manifest["entries"]) == ["evaluator.json", "evaluator.pt", "metrics.json", "train_state.pt"]
    (out / "notes.txt").write_text("mine")
    assert _train_ev(out, "--overwrite") == 0
    assert (out / "notes.txt").read_text() == "mine"
    assert json.loads((out / "evaluator.json").read_text())["epochs"] == 2
    assert sorted(os.listdir(tmp_path)) == ["ev"]


# ------------------------------------------------------------------------------ one unit; OS errors
def _full_disk(path, *a, **k):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))


def test_eval_failure_mid_write_keeps_the_earlier_results(tmp_path, evaluator, motions, monkeypatch, capsys):
    import smdm_plugin.io.files as files

    out = tmp_path / "res"
    assert cli.main(_eval_args(evaluator, motions, out)) == 0
    before = _snapshot(out)
    capsys.readouterr()
    monkeypatch.setattr(files, "atomic_write_text", _full_disk)  # metrics.md, after metrics.json was written
    assert cli.main(_eval_args(evaluator, motions, out) + ["--overwrite"]) == 1
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith("smdm eval: error: ") and line.endswith("metrics.md: No space left on device")
    assert ".res.partial" in line
    assert _snapshot(out) == before and sorted(os.listdir(tmp_path)) == ["res"]


def test_evaluator_failure_mid_write_is_one_line_then_resumes(tmp_path, monkeypatch, capsys):
    """evaluator train writes in --out itself (a long run: its state visible as it goes; docs/reliability.md)."""
    import smdm_plugin.io.files as files

    out = tmp_path / "ev"
    assert _train_ev(out, "--epochs", "1", "--seed", "1") == 0
    capsys.readouterr()
    monkeypatch.setattr(files, "atomic_write_json", _full_disk)  # evaluator.json, after evaluator.pt
    assert _train_ev(out, "--overwrite") == 1
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith("smdm evaluator: error: ") and line.endswith("evaluator.json: No space left on device")
    assert not os.path.exists(lock_path(out)) and not os.path.exists(partial_path(out))
    assert os.path.isfile(out / "train_state.pt")  # kept for --resume
    monkeypatch.undo()
    assert _train_ev(out, "--resume") == 0  # continues the failed run (its 2 epochs done)
    ref = tmp_path / "ref"
    assert _train_ev(ref) == 0
    _assert_same_weights(out, ref)
    assert sorted(os.listdir(tmp_path)) == ["ev", "ref"]


def _assert_same_weights(a: Path, b: Path) -> None:
    """Same weights, same per-epoch losses and held-out accuracies (wall times aside)."""
    sa = torch.load(a / "evaluator.pt", weights_only=True)
    sb = torch.load(b / "evaluator.pt", weights_only=True)
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    ja, jb = (json.loads((f / "evaluator.json").read_text()) for f in (a, b))
    assert [{k: v for k, v in h.items() if k != "seconds"} for h in ja["history"]] == \
        [{k: v for k, v in h.items() if k != "seconds"} for h in jb["history"]]
    assert ja["metrics"] == jb["metrics"] and ja["best_epoch"] == jb["best_epoch"]


# ------------------------------------------------------------------------------ resumable evaluator training
def test_evaluator_ctrl_c_then_resume_equals_one_run(tmp_path, monkeypatch, capsys):
    """Interrupted after epoch 1 of 3: its state in `--out` (written there as it goes); `--resume`
    continues it to the same weights as 3 epochs in one go."""
    import smdm_plugin.metrics.evaluator.train as tr

    real = tr.train_evaluator

    def interrupted(*a, on_epoch=None, **k):
        def cb(st):
            on_epoch(st)
            if st["epoch"] == 1:
                raise KeyboardInterrupt
        return real(*a, on_epoch=cb, **k)

    out = tmp_path / "ev"
    monkeypatch.setattr(tr, "train_evaluator", interrupted)
    assert _train_ev(out, "--epochs", "3") == 130
    assert "rerun with --resume to continue from epoch 1" in capsys.readouterr().err
    assert not os.path.exists(lock_path(out)) and not os.path.exists(partial_path(out))
    assert torch.load(out / "train_state.pt", weights_only=True)["epoch"] == 1
    monkeypatch.undo()
    assert _train_ev(out, "--epochs", "3", "--resume") == 0
    ref = tmp_path / "ref"
    assert _train_ev(ref, "--epochs", "3") == 0
    _assert_same_weights(out, ref)
    assert json.loads((out / "evaluator.json").read_text())["epochs"] == 3
    assert sorted(os.listdir(tmp_path)) == ["ev", "ref"]


def test_evaluator_resume_without_a_run_is_refused_and_leaves_nothing(tmp_path, capsys):
    assert _train_ev(tmp_path / "ev", "--resume") == 2
    assert "holds no run to continue" in _one_line(capsys.readouterr().err)
    assert os.listdir(tmp_path) == []


# ------------------------------------------------------------------------------ unreadable inputs
def test_an_empty_npy_among_the_motions_is_one_line(tmp_path, evaluator, motions, capsys):
    """0.4.0: an EOFError traceback from np.load. Now one line naming the file, exit 2, no output."""
    import shutil

    folder = tmp_path / "m"
    shutil.copytree(motions, folder)
    bad = sorted(folder.glob("*.npy"))[0]
    bad.write_bytes(b"")
    out = tmp_path / "res"
    capsys.readouterr()
    assert cli.main(_eval_args(evaluator, folder, out)) == 2
    line = _one_line(capsys.readouterr().err)
    assert str(bad) in line and "not a readable .npy file" in line
    assert not out.exists()


# ------------------------------------------------------------------------------ resume by content
def _captioned(root: Path) -> Path:
    """A HumanML3D-format folder with captions (texts/<id>.txt)."""
    write_humanml3d(root)
    (root / "texts").mkdir()
    words = ["walks forward", "jumps up", "turns left", "waves a hand", "sits down", "kicks"]
    for split in ("train", "val"):
        for k, i in enumerate((root / f"{split}.txt").read_text().split()):
            w = words[(k + (split == "val")) % len(words)]
            tokens = " ".join(f"{t}/VERB" for t in w.split())
            (root / "texts" / f"{i}.txt").write_text(f"a person {w}#a/DET person/NOUN {tokens}#0.0#0.0\n")
    return root


def test_evaluator_resume_knows_the_data_by_content(tmp_path, capsys):
    """0.4.0 compared the path: an identical copy elsewhere was refused (other settings), data
    changed in place resumed. Now the data is known by content; a change is named."""
    data = _captioned(tmp_path / "data")
    copy = tmp_path / "elsewhere"
    out = tmp_path / "ev"
    assert _train_ev(out, "--data", str(data), "--epochs", "1", "--ae-epochs", "1") == 0
    shutil.copytree(data, copy)
    capsys.readouterr()
    assert _train_ev(out, "--data", str(copy), "--epochs", "2", "--ae-epochs", "1", "--resume") == 0
    f = copy / "new_joint_vecs" / "train001.npy"
    a = np.load(f)
    a[3, 7] += 1.0  # same name, same size: only the content tells
    np.save(f, a)
    before = _snapshot(out)
    capsys.readouterr()
    assert _train_ev(out, "--data", str(copy), "--epochs", "3", "--ae-epochs", "1", "--resume") == 2
    line = _one_line(capsys.readouterr().err)
    assert "was trained on other data" in line and "changed: train/train001" in line, line
    assert _snapshot(out) == before and not os.path.exists(lock_path(out))
