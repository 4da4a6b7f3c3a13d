"""The `smdm` commands run as a user runs them (`python -m smdm_plugin ...` in a subprocess): exit
status, the one-line message, no traceback, and earlier files untouched. Covers the global entry,
`ablate` (arguments, config files, existing results, Ctrl-C then rerun), `keyframes` and `run`."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from helpers.synthetic_data import write_humanml3d

from helpers.paths import MOCAP
TINY_GRID = """name: tiny
steps: {steps}
batch: 2
max_frames: 48
diffusion_steps: 5
model: {{latent_dim: 16, num_layers: 1, num_heads: 2, ff_size: 32}}
eval: {{samples: 1, frames: 40, keyframe_motions: 1}}
variants:
  - {{name: dense, dense: true}}
  - {{name: sparse}}
"""


def smdm(*args: str, cwd=None, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "smdm_plugin", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout)


def user_error(r: subprocess.CompletedProcess, needle: str, code: int = 2) -> None:
    """Exit ``code``, ``needle`` in stderr's last line, which starts with the command, no traceback."""
    last = r.stderr.strip().splitlines()[-1] if r.stderr.strip() else ""
    assert r.returncode == code, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr and last.startswith("smdm") and needle in last, r.stderr


def snapshot(folder: Path):
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------ smdm
def test_global_entry():
    r = smdm()
    assert r.returncode == 2 and "usage: smdm <command>" in r.stderr and "keyframes" in r.stderr
    user_error(smdm("bnech"), "unknown command 'bnech'; did you mean 'bench'?")
    r = smdm("--version")
    assert r.returncode == 0 and r.stdout.startswith("smdm-plugin ")
    r = smdm("--help")
    assert r.returncode == 0 and all(c in r.stdout for c in ("bench", "ablate", "demo", "run", "keyframes"))
    user_error(smdm("--version", "extra"), "smdm: error: --version takes no arguments, got 'extra'")
    r = smdm("help", "keyframes")                   # a command's own help
    assert r.returncode == 0 and r.stdout.startswith("usage: smdm keyframes"), r
    user_error(smdm("help", "bnech"), "unknown command 'bnech'; did you mean 'bench'?")
    user_error(smdm("help", "demo", "train"), "help takes at most one command name, got 'demo train'")


# ------------------------------------------------------------------------------ smdm ablate
@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_humanml3d(tmp_path_factory.mktemp("hml"))


@pytest.mark.parametrize("args,needle", [
    (["--steps", "0"], "argument --steps: must be an integer >= 1, got 0"),
    (["--device", "tpu"], "argument --device: expected auto, cpu, cuda, cuda:N or mps, got 'tpu'"),
    (["--config", "missing.yaml"], "--config 'missing.yaml' is neither a file nor a packaged grid"),
    (["--config", "quick", "--only", "dnese"], "argument --only: unknown variant(s) 'dnese'; did you mean 'dense'?"),
    (["--resume", "--overwrite"], "argument --overwrite: not allowed with argument --resume"),
])
def test_ablate_bad_arguments(tmp_path, args, needle):
    r = smdm("ablate", "--out", tmp_path / "out", *args, cwd=tmp_path)
    user_error(r, needle)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("text,needle", [
    ("steps: [3\n", "not valid YAML"),
    ("stesp: 3\nvariants: [{name: a}]\n", "unknown key 'stesp'; did you mean 'steps'?"),
    ("variants: [{name: sparse (VW)}, {name: Sparse VW}]\n", "have the same folder name 'sparse-vw'"),
])
def test_ablate_bad_config_files_name_the_file(tmp_path, data, text, needle):
    cfg = tmp_path / "grid.yaml"
    cfg.write_text(text)
    r = smdm("ablate", "--config", cfg, "--data", data, "--out", tmp_path / "out")
    user_error(r, needle)
    assert str(cfg) in r.stderr.strip().splitlines()[-1]


def test_ablate_refuses_existing_results_and_leaves_them_untouched(tmp_path, data):
    out = tmp_path / "out"
    (out / "dense").mkdir(parents=True)
    (out / "config.yaml").write_text("name: old\n")
    (out / "dense" / "result.json").write_text('{"name": "dense", "status": "ok"}')
    before = snapshot(out)
    user_error(smdm("ablate", "--config", "quick", "--data", data, "--out", out),
               "already holds ablation results; pass --resume")
    assert snapshot(out) == before
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("precious")
    user_error(smdm("ablate", "--config", "quick", "--data", data, "--out", tmp_path / "mine", "--resume"),
               "non-empty folder without smdm ablate results")
    assert (tmp_path / "mine" / "thesis.tex").read_text() == "precious"
    (tmp_path / "file").write_text("precious")
    user_error(smdm("ablate", "--config", "quick", "--data", data, "--out", tmp_path / "file"), "is not a folder")
    assert (tmp_path / "file").read_text() == "precious"


def test_ablate_grid_file_is_an_input_apart_from_the_output(tmp_path, data):
    """Every path a command reads counts in the overlap check (0.7.0 ran with the grid inside --out)."""
    out = tmp_path / "runs"
    out.mkdir()
    (out / "grid.yaml").write_text(TINY_GRID.format(steps=1))
    before = snapshot(out)
    for extra in ([], ["--overwrite"]):
        user_error(smdm("ablate", "--config", out / "grid.yaml", "--data", data, "--out", out, "--threads", "1",
                        *extra), "contains the input --config")
    assert snapshot(out) == before


def test_ablate_ctrl_c_halfway_then_resume(tmp_path, data):
    """SIGINT while the second variant trains: exit 130, one line, the first result whole; the
    rerun refuses without --resume, and with it runs only what is missing; an invalid variant
    fails alone (exit 1, the others finish)."""
    cfg = tmp_path / "grid.yaml"
    cfg.write_text(TINY_GRID.format(steps=150) + "  - {name: broken, sparse: {reduction: 1.5, lipschitz: 'no'}}\n")
    out = tmp_path / "out"
    args = [sys.executable, "-m", "smdm_plugin", "ablate", "--config", str(cfg), "--data", str(data), "--out",
            str(out), "--no-progress", "--threads", "1"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    while not (out / "dense" / "result.json").exists():
        assert proc.poll() is None and time.time() - t0 < 240, "the first variant did not finish"
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    if (out / "sparse" / "result.json").exists():
        pytest.skip("the second variant finished before the signal (machine too fast for this timing)")
    assert proc.returncode == 130 and "Traceback" not in stderr and "interrupted" in stderr, stderr
    assert json.loads((out / "dense" / "result.json").read_text())["status"] == "ok"
    assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]
    assert "| sparse | not run |" in (out / "results.md").read_text()
    assert "| broken | not run |" in (out / "results.md").read_text()

    before = snapshot(out)
    user_error(smdm(*args[3:]), "pass --resume")
    assert snapshot(out) == before
    r = smdm(*args[3:], "--resume")
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    assert "dense: reused (same provenance" in r.stdout and "sparse: loss" in r.stdout
    assert "| dense | ok |" in r.stdout and "| sparse | ok |" in r.stdout and "| broken | failed |" in r.stdout
    assert "broken failed: ValueError: SparseConfig.reduction=1.5" in r.stdout
    assert snapshot(out)["dense/result.json"] == before["dense/result.json"]


# ------------------------------------------------------------------------------ smdm keyframes
def test_keyframes_bad_arguments(tmp_path):
    user_error(smdm("keyframes", "--reductions", "1.5"), "argument --reductions: must be a finite number in [0, 1)")
    user_error(smdm("keyframes", "--reductions", "-0.2"), "argument --reductions")
    user_error(smdm("keyframes", "--frame-index-scale", "-1"), "argument --frame-index-scale: must be a finite")
    # a huge one overflowed the selection features (a traceback in 0.10.6)
    user_error(smdm("keyframes", "--frame-index-scale", "1e300"), "argument --frame-index-scale: must be a finite "
               "number in [0, 100]")
    user_error(smdm("keyframes", tmp_path / "missing.bvh"), "argument bvh: no such file")
    # a mistyped option is named, not its value read as a BVH path (0.10.6: "argument bvh: no such file: '0'")
    user_error(smdm("keyframes", "--rates", "0"), "unrecognized arguments: --rates")
    user_error(smdm("evaluator", "check", "--bogus", "1"), "unrecognized arguments: --bogus")
    user_error(smdm("evaluator", "check", tmp_path / "none"), "argument EDIR: no such folder")
    user_error(smdm("keyframes", tmp_path), f"smdm keyframes: no .bvh file in {tmp_path}")
    user_error(smdm("keyframes", "--plot", tmp_path / "x.gif"), "argument --plot: expected a file name ending in .png")


@pytest.mark.skipif(not (MOCAP / "02_02.bvh").exists(), reason="../shared/data/cmu-mocap not available")
def test_keyframes_names_skipped_files_and_never_overwrites_the_plot(tmp_path):
    text = (MOCAP / "02_02.bvh").read_text()  # a short CMU clip: 299 frames at 120 fps
    n = int(text.split("Frames:")[1].split()[0])
    lines = text.splitlines(keepends=True)
    clips = tmp_path / "clips"
    clips.mkdir()
    (clips / "good.bvh").write_text(text)
    (clips / "extra_row.bvh").write_text(text.replace(f"Frames: {n}", f"Frames: {n - 1}"))
    (clips / "truncated.bvh").write_text("".join(lines[: len(lines) - 20]))
    (clips / "zero_time.bvh").write_text(text.replace("Frame Time:", "Frame Time: 0 #"))
    plot = tmp_path / "kf.png"
    r = smdm("keyframes", ".", "--reductions", "0.8", "--plot", plot, cwd=clips)
    assert r.returncode == 0, r.stderr
    assert "| vw |" in r.stdout and plot.stat().st_size > 0
    assert "skipping ./truncated.bvh: read_bvh: ./truncated.bvh: truncated motion" in r.stderr
    assert "skipping ./zero_time.bvh: read_bvh: ./zero_time.bvh, line 187: Frame Time: must be" in r.stderr
    assert f"note: read_bvh: ./extra_row.bvh: Frames: {n - 1} declared, {n} rows present" in r.stderr
    before = plot.read_bytes()
    user_error(smdm("keyframes", clips / "good.bvh", "--reductions", "0.8", "--plot", plot),
               "--plot '" + str(plot) + "' exists; pass --overwrite")
    assert plot.read_bytes() == before
    r = smdm("keyframes", clips / "good.bvh", "--reductions", "0.8", "--plot", plot, "--overwrite")
    assert r.returncode == 0 and sorted(p.name for p in tmp_path.iterdir()) == ["clips", "kf.png"]


# ------------------------------------------------------------------------------ smdm run
@pytest.fixture
def fake_mdm(tmp_path):
    """A folder with MDM's layout (what `smdm run` detects)."""
    for f in ("model/mdm.py", "utils/model_util.py"):
        (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / f).write_text("")
    return tmp_path


def test_run_bad_arguments(tmp_path, fake_mdm):
    user_error(smdm("run", "--repo", tmp_path / "nope", "--", sys.executable, "-c", "1"), "is not a directory")
    (tmp_path / "empty").mkdir()
    user_error(smdm("run", "--repo", tmp_path / "empty", "--", sys.executable, "-c", "1"),
               "is not a checkout smdm-plugin knows")
    user_error(smdm("run", "--repo", fake_mdm), "no command given")
    user_error(smdm("run", "--repo", fake_mdm, "--integration", "mdn", "--", "python"), "invalid choice: 'mdn'")
    user_error(smdm("run", "--repo", fake_mdm, "--", "no-such-program-xyz"),
               "command not found: 'no-such-program-xyz'", code=127)


def test_run_passes_the_exit_status_and_installs_the_hooks(fake_mdm):
    r = smdm("run", "--repo", fake_mdm, "--", sys.executable, "-c",
             "import os, sys; print(os.environ['SMDM_INTEGRATION'], os.getcwd()); sys.exit(3)")
    assert r.returncode == 3 and r.stdout.split() == ["mdm", str(fake_mdm)]
    r = smdm("run", "--repo", fake_mdm, "--", sys.executable, "-c",
             "import os, signal; os.kill(os.getpid(), signal.SIGTERM)")
    assert r.returncode == 128 + signal.SIGTERM and "Traceback" not in r.stderr


# ------------------------------------------------------------------------------ shared argument types
def test_argument_types(tmp_path, monkeypatch):
    import argparse

    import torch

    from smdm_plugin.apps.common.args import device_type, existing_path, float_range, int_range, resolve_device

    assert device_type("auto") == "auto" and device_type("cpu") == "cpu"
    assert resolve_device("cpu") == torch.device("cpu")
    for bad, needle in (("gpu", "expected auto, cpu, cuda, cuda:N or mps"), ("CUDA", "expected auto"),
                        ("meta", "expected auto")):
        with pytest.raises(argparse.ArgumentTypeError, match=needle):
            device_type(bad)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(argparse.ArgumentTypeError, match="cuda: CUDA is not available on this machine"):
        device_type("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert device_type("cuda:1") == "cuda:1"
    with pytest.raises(argparse.ArgumentTypeError, match="cuda:2: this machine has 2 CUDA device"):
        device_type("cuda:2")
    assert int_range(1)("3") == 3 and float_range(0, 1, hi_open=True)("0.5") == 0.5
    with pytest.raises(argparse.ArgumentTypeError, match="must be an integer in \\[1, 4\\], got 5"):
        int_range(1, 4)("5")
    with pytest.raises(argparse.ArgumentTypeError, match="must be a finite number > 0, got inf"):
        float_range(0, lo_open=True)("inf")
    (tmp_path / "f").write_text("")
    assert existing_path("file")(str(tmp_path / "f")) == str(tmp_path / "f")
    with pytest.raises(argparse.ArgumentTypeError, match="is a folder, expected a file"):
        existing_path("file")(str(tmp_path))
    with pytest.raises(argparse.ArgumentTypeError, match="is not a folder"):
        existing_path("dir")(str(tmp_path / "f"))


@pytest.mark.parametrize("command", [["train"], ["demo"], ["inbetween"], ["eval"], ["evaluator", "train"]])
def test_every_seed_is_bounded_to_what_torch_takes(command):
    """0.10.6: ``--seed 99999999999999999999`` was a traceback (``Overflow when unpacking long long``) in
    smdm inbetween / demo, and an unnamed error in smdm train."""
    user_error(smdm(*command, "--seed", "99999999999999999999"),
               "argument --seed: must be an integer in [0, 9223372036854775807]")


@pytest.mark.parametrize("args,needle", [
    # multimodality needs two generations per caption; captions for it need it on (0.10.6 dropped both silently)
    (["eval", "--model", "{d}", "--evaluator", "{d}", "--out", "{d}/o", "--mm-repeats", "1"],
     "argument --mm-repeats: must be 0 (off) or >= 2"),
    (["eval", "--model", "{d}", "--evaluator", "{d}", "--out", "{d}/o", "--mm-repeats", "0", "--mm-captions", "5"],
     "argument --mm-captions: multimodality is off"),
    (["eval", "--model", "{d}", "--evaluator", "{d}", "--out", "{d}/o", "--mm-captions", "5"],
     "argument --mm-captions: multimodality is off"),
    (["demo", "--no-progress", "--progress"], "argument --progress: not allowed with argument --no-progress"),
    (["demo", "--quiet", "--progress"], "argument --progress: not allowed with argument --quiet"),
    (["demo", "--progress", "--quiet"], "argument --quiet: not allowed with argument --progress"),
    # the study's parser does not take a grid's options: named as such, not "unrecognized" (0.10.6)
    (["ablate", "--config", "quality_compute", "--quick", "--steps", "1"], "argument --steps: an ablation grid's option"),
    (["ablate", "--config", "quick", "--quick"], "argument --quick: runs a study config's quick variant; --config "
                                                "'quick' is an ablation grid"),
    (["inbetween", "--model", "{d}", "--keyframes", "", "--out", "{d}/i"], "argument --keyframes: no such file: ''"),
    # smdm bench: sizes bounded (a huge one was an allocation traceback), settings its mode ignores refused
    (["bench", "--batch", "99999999999"], "argument --batch: must be an integer in [1, 65536]"),
    (["bench", "keyframes", "--dims", "99999999999"], "argument --dims: must be an integer in [1, 4096]"),
    (["bench", "--family", "motiondiffuse", "--backend", "masked"], "argument --backend: --family motiondiffuse has "
                                                                      "no keyframe attention backend"),
    (["bench", "--backend", "masked", "--compile", "default"], "argument --backend: a compiled model runs the compact"),
    (["bench", "--arch", "dip", "--frames", "100"], "argument --frames: --arch dip runs DiP's own 20 prefix"),
    (["bench", "--device", "cpu", "--quick", "--out", "{d}"], "argument --out: expected a file path"),
    (["run", "--repo", "", "--", "python", "-c", "1"], "argument --repo: expected a non-empty string"),
    (["render", "{d}", "--out", "{d}/x.gif"], "argument MOTION: '{d}' is a folder, expected a file"),
])
def test_options_that_cannot_apply_and_wrong_paths_are_named(tmp_path, args, needle):
    d = str(tmp_path)
    user_error(smdm(*(x.replace("{d}", d) for x in args)), needle.replace("{d}", d))


def test_a_corrupt_checkpoint_is_named_in_a_whole_sentence(tmp_path):
    from smdm_plugin.io.checkpoint_files import read_state_dict

    (tmp_path / "bad.pt").write_bytes(b"not a zip archive at all")
    with pytest.raises(ValueError) as e:
        read_state_dict(str(tmp_path / "bad.pt"))
    assert str(e.value).startswith(f"{tmp_path / 'bad.pt'}: not a readable checkpoint (truncated or corrupt: ")
    assert str(e.value).endswith(")") and "your checkpoint file is)" not in str(e.value)
