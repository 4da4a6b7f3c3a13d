"""The commands under faults and unusable input: a full disk is one line naming the file (exit 1, nothing left that
blocks the next run), `smdm train` writes each checkpoint in --out as it goes, `--resume` knows the
data by content, and unusable inputs (empty .npy, clips shorter than a keyframe window, a tampered
result.json) are one line with the documented exit status, never a traceback."""
from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

import smdm_plugin.support.atomic as atomic
from smdm_plugin.apps import ablate, cli
from smdm_plugin.apps import train as train_cli
from smdm_plugin.apps.common import keyframe_study as ks
from smdm_plugin.io.outdir import MANIFEST, lock_path, partial_path
from smdm_plugin.training import trainer as T

from helpers.grids import GRID_HEAD
from helpers.commands import TINY_TRAIN, TORCH_FULL_DISK

TINY = [*TINY_TRAIN, "--min-frames", "20"]


@pytest.fixture
def data(synthetic_hml) -> Path:
    return synthetic_hml


@pytest.fixture
def full_disk(monkeypatch):
    """torch.save fails as on a full disk (the RuntimeError of its zip writer; the disk reports no
    free space)."""
    real = torch.save

    def save(obj, f, *a, **k):
        if hasattr(f, "write"):
            f.write(b"PK\x03\x04")
        raise RuntimeError(TORCH_FULL_DISK)

    monkeypatch.setattr(torch, "save", save)
    monkeypatch.setattr(atomic, "_free_bytes", lambda folder: 0)
    return real


def _status(argv) -> int:
    """``smdm <argv>``'s exit status (argparse errors exit by SystemExit, as from the shell)."""
    try:
        return cli.main(argv)
    except SystemExit as e:
        return int(e.code)


def _last_line(err: str) -> str:
    assert "Traceback" not in err
    return err.strip().splitlines()[-1]


# ------------------------------------------------------------------------------ full disk
def test_train_on_a_full_disk_is_one_line_and_blocks_nothing(tmp_path, data, full_disk, monkeypatch, capsys):
    """0.4.0: a traceback (RuntimeError: [enforce fail at inline_container.cc...])."""
    out = tmp_path / "run"
    rc = cli.main(["train", "--data", str(data), "--out", str(out), "--steps", "2", *TINY])
    line = _last_line(capsys.readouterr().err)
    assert rc == 1 and line == f"smdm train: error: {out / 'model000000002.pt'}: No space left on device"
    assert not os.path.exists(lock_path(out)) and not [n for n in os.listdir(out) if n.endswith(".tmp")]
    monkeypatch.undo()
    assert train_cli.main(["--data", str(data), "--out", str(out), "--steps", "2", "--overwrite", *TINY]) == 0


def test_demo_on_a_full_disk_is_one_line_and_leaves_nothing(tmp_path, full_disk, capsys):
    out = tmp_path / "demo"
    rc = cli.main(["demo", "--quick", "--no-gif", "--no-evaluator", "--out", str(out), "--threads", "1"])
    line = _last_line(capsys.readouterr().err)
    assert rc == 1 and line.startswith("smdm demo: error: ") and line.endswith(".pt: No space left on device")
    assert sorted(os.listdir(tmp_path)) == []  # a short command: all or nothing; no lock, no partial folder


# ------------------------------------------------------------------------------ long runs: visible as they go
def test_train_checkpoints_appear_in_out_as_they_are_made(tmp_path, data, monkeypatch):
    """0.4.0 wrote into .<out>.partial: --out did not exist until the end."""
    out, seen = tmp_path / "run", {}
    real_step = T.Trainer.step

    def step(self):
        if self.step_count == 5:  # mid-run: the checkpoint of step 4 is in --out, loadable
            seen["files"] = sorted(os.listdir(out))
            seen["model"] = T.load_trained(str(out))
            seen["locked"] = os.path.exists(lock_path(out))
        return real_step(self)

    monkeypatch.setattr(T.Trainer, "step", step)
    assert train_cli.main(["--data", str(data), "--out", str(out), "--steps", "6", "--save-every", "2",
                           "--sparse", *TINY]) == 0
    assert {"model000000002.pt", "model000000004.pt", T.TRAIN_STATE_FILENAME, MANIFEST} <= set(seen["files"])
    assert seen["locked"] and seen["model"][1] is not None  # the lock is held; a sparse model loads
    assert not os.path.exists(partial_path(out)) and not os.path.exists(lock_path(out))
    assert (out / "model000000006.pt").exists()


# ------------------------------------------------------------------------------ resume by content
def test_resume_knows_the_data_by_content(tmp_path, data, capsys):
    """0.4.0 compared the path: an identical copy elsewhere was refused, data changed in place resumed."""
    out, copy = tmp_path / "run", tmp_path / "elsewhere"
    args = ["--out", str(out), "--save-every", "1", *TINY]
    assert train_cli.main(["--data", str(data), "--steps", "2", *args]) == 0
    shutil.copytree(data, copy)
    capsys.readouterr()
    assert train_cli.main(["--data", str(copy), "--steps", "3", "--resume", *args]) == 0  # the same data
    assert "resumed at step 2" in capsys.readouterr().out
    f = copy / "new_joint_vecs" / "train001.npy"
    a = np.load(f)
    a[3, 7] += 1.0  # same name, same size: only the content tells
    np.save(f, a)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert train_cli.main(["--data", str(copy), "--steps", "4", "--resume", *args]) == 2
    err = capsys.readouterr().err
    assert f"was trained on other data (--data {copy}: changed: new_joint_vecs/train001.npy)" in err
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
    assert not os.path.exists(lock_path(out))


# ------------------------------------------------------------------------------ inputs
@pytest.fixture(scope="module")
def demo_model(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("demo") / "d"
    assert cli.main(["demo", "--quick", "--no-gif", "--no-evaluator", "--out", str(out), "--threads", "1"]) == 0
    return out / "dense"


@pytest.mark.parametrize("command", ["render", "inbetween"])
def test_an_empty_npy_is_one_line(tmp_path, command, demo_model, capsys):
    """0.4.0: an EOFError traceback."""
    empty = tmp_path / "m.npy"
    empty.write_bytes(b"")
    argv = {"render": ["render", str(empty), "--out", str(tmp_path / "m.gif")],
            "inbetween": ["inbetween", "--model", str(demo_model), "--keyframes", str(empty), "--out",
                          str(tmp_path / "o"), "--threads", "1"]}[command]
    capsys.readouterr()
    rc = _status(argv)
    line = _last_line(capsys.readouterr().err)
    assert rc == 2 and f"{empty}: not a readable .npy file" in line
    assert sorted(os.listdir(tmp_path)) == ["m.npy"]


@pytest.fixture
def short_clips(monkeypatch):
    """The motion source gives only clips shorter than a keyframe window (40 frames)."""
    from smdm_plugin.apps import demo
    from smdm_plugin.io.embedded import embedded_clips

    clips = [(n, j[:30]) for n, j in embedded_clips()[:3]]

    def source(*a, **k):
        return "short clips", ["a.bvh"], clips

    monkeypatch.setattr(ks, "motion_source", source)
    monkeypatch.setattr(demo, "motion_source", source)
    return clips


@pytest.mark.parametrize("argv", [["keyframes"], ["keyframes", "--plot", "{tmp}/k.png"],
                                  ["demo", "--quick", "--no-gif", "--no-evaluator", "--frames", "20",
                                   "--out", "{tmp}/d"]])
def test_clips_shorter_than_a_keyframe_window_are_one_line(tmp_path, short_clips, argv, capsys):
    """0.4.0: a table of NaN (keyframes), an IndexError traceback (--plot, demo)."""
    rc = _status([a.format(tmp=tmp_path) for a in argv])
    out, err = capsys.readouterr()
    assert rc == 2 and "nan" not in out
    assert _last_line(err).endswith("no clip has the 40 frames (at 20 fps) a keyframe window needs (the longest, "
                                    f"{short_clips[0][0]}, has 30); give longer clips")
    assert os.listdir(tmp_path) == []


GRID = GRID_HEAD + "  - {name: dense, dense: true}\n"


def test_a_tampered_result_json_is_reported_not_a_crash(tmp_path, data, monkeypatch, capsys):
    """0.4.0: "Unknown format code 'f' for object of type 'str'" (a traceback) under --resume."""
    def run_variant(cfg, variant, data, device, progress=False, dist=None, checkpoint_dir=None):
        return {"name": variant["name"], "status": "ok", "steps": 2, "final_loss": 1.0, "best_loss": 0.9,
                "val_loss": 1.5, "steps_per_s": 10.0, "train_s": 0.1, "sample_s": 0.1, "keyframe_error_mm": None,
                "ees": 3.0, "losses": [1.0, 1.0], "sparse_config": None}

    monkeypatch.setattr(ablate, "run_variant", run_variant)
    (tmp_path / "g.yaml").write_text(GRID)
    argv = ["--config", str(tmp_path / "g.yaml"), "--out", str(tmp_path / "out"), "--data", str(data),
            "--no-progress"]
    assert ablate.main(argv) == 0
    res = tmp_path / "out" / "dense" / "result.json"
    rec = json.loads(res.read_text())
    rec["final_loss"] = "0.5"  # edited by hand
    res.write_text(json.dumps(rec))
    capsys.readouterr()
    rc = ablate.main(argv + ["--resume"])
    out, err = capsys.readouterr()
    assert "Traceback" not in err and "Unknown format code" not in out + err
    # a result that cannot be reported is corrupt: --resume runs that variant again (docs/bench_ablate_demo.md)
    assert "dense: replacing corrupt result" in out + err and "final_loss='0.5': expected a number or null" in out + err
    assert rc == 0 and json.loads(res.read_text())["final_loss"] == 1.0


def test_result_records_are_checked_before_they_are_reported():
    """The records `smdm ablate` (and its quality-versus-compute study) reuse under --resume."""
    from smdm_plugin.apps.ablate.report import check_record

    assert check_record({"final_loss": 1.0, "ees": None, "losses": [1.0, 2]}) is None
    assert check_record({"jitter": True}) == "jitter=True: expected a number or null"
    assert check_record({"losses": [1.0, "x"]}) == "losses: expected a list of numbers"
    assert check_record({"snapshots": [{"kind": "steps", "at": 10, "fid": "0.3"}]}) == \
        "snapshots[0].fid='0.3': expected a number or null"
    assert check_record({"snapshots": [{"kind": "steps", "at": 10, "fid": None, "loss": 0.1}]}) is None


# ------------------------------------------------------------------------------ an output that cannot be written
def _unwritable_outputs(tmp_path: Path):
    """``(where, --out inside it, the reason the message gives)``: a path under a regular file (any
    user), and on Linux a folder that takes no new file for any user, root included (``/proc``)."""
    (tmp_path / "afile").write_text("mine")
    yield tmp_path / "afile" / "sub", "is a file, not a folder"
    if os.path.isdir("/proc/self"):
        yield Path("/proc") / f"smdm-test-{os.getpid()}", "takes no new file"


def _output_argv(command: str, out: Path, tmp_path: Path, data: Path):
    grid = tmp_path / "g.yaml"
    grid.write_text(GRID)
    return {"train": ["train", "--data", str(data), "--out", str(out), "--steps", "2", *TINY],
            "demo": ["demo", "--quick", "--no-gif", "--no-evaluator", "--out", str(out), "--threads", "1"],
            "bench": ["bench", "--quick", "--out", str(out / "b.md"), "--threads", "1"],
            "ablate": ["ablate", "--config", str(grid), "--out", str(out), "--data", str(data), "--no-progress"],
            "clips": ["clips", "export", "02_01", "--out", str(out.parent / "walk.npy")]}[command]


@pytest.mark.parametrize("command", ["train", "demo", "bench", "ablate", "clips"])
def test_an_output_that_cannot_be_written_is_refused_before_the_run(tmp_path, data, command, monkeypatch, capsys):
    """0.10.5: `smdm demo --out /proc/demo` said `/proc/..demo.lock.<pid>.<hex>.tmp: No such file or
    directory` (a temporary file of the lock, not the argument), `smdm bench --out /proc/b.md` ran the
    whole benchmark first, and the exit status differed by command. Now: exit 2, one line naming --out
    and why, nothing run and nothing left in the input's folder."""
    ran = []
    monkeypatch.setattr(ablate, "run_variant", lambda *a, **k: ran.append(a))
    monkeypatch.setattr(T.Trainer, "__init__", lambda *a, **k: ran.append(a))
    from smdm_plugin.apps import bench
    monkeypatch.setattr(bench, "run_bench", lambda *a, **k: ran.append(a))
    for out, reason in _unwritable_outputs(tmp_path):
        argv = _output_argv(command, out, tmp_path, data)
        before = sorted(os.listdir(tmp_path))
        rc = _status(argv)
        err = capsys.readouterr()
        line = _last_line(err.err)
        assert rc == 2 and line.startswith(f"smdm {command}: ") and "--out" in line and reason in line, line
        assert ".tmp" not in line and ".lock" not in line
        assert sorted(os.listdir(tmp_path)) == before and not ran and "|" not in err.out   # no table: nothing ran


def test_check_writable_probes_the_folder_that_would_hold_the_file(tmp_path, monkeypatch):
    from smdm_plugin.io.files import OutputUnwritableError, check_writable

    check_writable(tmp_path / "new" / "deeper" / "x.json", "--out")     # folders to make: probed where they start
    assert os.listdir(tmp_path) == []                                    # the probe is gone, nothing made
    (tmp_path / "f").write_text("mine")
    with pytest.raises(OutputUnwritableError, match=r"--out '.*f/x' cannot be created: '.*f' is a file"):
        check_writable(tmp_path / "f" / "x", "--out")
    if os.path.isdir("/proc/self"):
        with pytest.raises(OutputUnwritableError, match=r"'/proc' takes no new file"):
            check_writable("/proc/smdm-out", "--out")
        with pytest.raises(OutputUnwritableError, match=r"'/proc/self' takes no new file"):
            check_writable("/proc/self", "--out", inside=True)
    assert (tmp_path / "f").read_text() == "mine"
    with monkeypatch.context() as m:      # no folder up to the root (a Windows drive that is not there): refused
        m.setattr(os.path, "isdir", lambda p: False)
        m.setattr(os.path, "lexists", lambda p: False)
        with pytest.raises(OutputUnwritableError, match="does not exist"):
            check_writable(tmp_path / "x", "--out")


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs a folder that takes no new file (Linux /proc)")
def test_an_atomic_write_that_cannot_start_names_the_file_not_its_temporary():
    with pytest.raises(OSError) as e:
        atomic.atomic_write_text("/proc/smdm-out.json", "{}")
    assert e.value.filename == "/proc/smdm-out.json"


@pytest.mark.parametrize("argv,kind", [
    (["train", "--data", "{data}", "--steps", "2"], "folder"), (["demo", "--quick"], "folder"),
    (["bench", "--quick"], "file"), (["clips", "export", "02_01"], "file"), (["render", "{data}/walk.npy"], "file"),
    (["ablate", "--config", "quick"], "folder"), (["ablate", "--config", "quality_compute"], "folder"),
    (["inbetween", "--keyframes", "{data}/Mean.npy"], "folder"), (["eval", "--motions", "{data}"], "folder"),
    (["evaluator", "train"], "folder"), (["keyframes", "--plot"], "file")])
def test_an_empty_output_path_is_refused_not_read_as_none_or_here(tmp_path, data, argv, kind, monkeypatch, capsys):
    """0.10.5: `smdm bench --out ''` ran and wrote nothing, `smdm clips export 02_01 --out ''` wrote
    02_01.npy, `smdm demo --out ''` refused '.' (the working folder): an empty path was read as no
    option or as here. Now every output option refuses it by name (exit 2)."""
    monkeypatch.chdir(tmp_path)
    argv = [a.replace("{data}", str(data)) for a in argv]
    option = "--plot" if argv[0] == "keyframes" else "--out"
    if option == "--out":
        argv += ["--out", ""]
    else:
        argv += [""]
    before = sorted(os.listdir(tmp_path))
    assert _status(argv) == 2
    line = _last_line(capsys.readouterr().err)
    assert line.endswith(f"argument {option}: expected a {kind} path, got ''"), line
    assert sorted(os.listdir(tmp_path)) == before
