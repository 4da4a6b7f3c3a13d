"""MotionDiffuse end to end, with the patch, the import hooks and the ``smdm run`` launcher: train
a tiny sparse MotionTransformer on cmu-humanml3d (CPU) with upstream's ``tools/train.py``, save,
and generate with upstream's ``tools/visualization.py`` from the checkpoint.

Skipped unless ``SMDM_MOTIONDIFFUSE_ROOT`` points at a MotionDiffuse checkout (the repo root,
holding text2motion/; read-only, it is copied). Needs: openai-clip (--no-deps), ftfy, scipy,
matplotlib, tqdm; mmcv, cv2 and spacy are stubbed by the harness when missing, CLIP is random
with a 2-layer text transformer. MotionDiffuse is S-Lab licensed (non-commercial); it is only run
here, never copied into this repository.

What is checked (each would fail if the integration were wrong):

* ``--sparse*`` are accepted by upstream's option parser; ``opt.txt`` and
  ``model/sparse_config.json`` carry them;
* the checkpoint's encoder has ``smdm_sparse_version`` and the Lipschitz ``joint_embed``;
* every training iteration selected a keyframe mask with about ``1 - reduction`` of the valid
  frames, none past a motion's length; the logged loss is finite (the hooks and launcher runs
  keep upstream's autograd anomaly detection, so a NaN in any backward op fails them) and goes
  down over 15 iterations (patch run);
* only the keyframe tokens of each call reach the decoder blocks (training and sampling);
* generation loads the checkpoint (strict: a dense model would not load it), takes a sparse
  sampling mask at every one of the ``diffusion_steps`` steps, and gives finite joints
  ``[60, 22, 3]``.
"""
import json
import os
import pickle
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
from _upstream import HERE, LAUNCHER, PATCHES, REPO, find_humanml3d

ROOT = os.environ.get("SMDM_MOTIONDIFFUSE_ROOT")
PATCH = os.path.join(PATCHES, "motiondiffuse.patch")
DATA = find_humanml3d() or ""

pytestmark = [pytest.mark.skipif(not ROOT, reason="SMDM_MOTIONDIFFUSE_ROOT not set"),
              pytest.mark.skipif(not DATA, reason="no HumanML3D-format data (SMDM_HUMANML3D_DIR)")]

REDUCTION, STEPS, FRAMES = 0.8, 50, 60
UPSTREAM_FILES = ("options/train_options.py", "options/evaluate_options.py", "tools/train.py",
                  "tools/visualization.py", "trainers/ddpm_trainer.py")


def prepare(run: str, patch: bool = True) -> str:
    shutil.copytree(ROOT, run, ignore=shutil.ignore_patterns(".git", "figures", "checkpoints"))
    t2m = os.path.join(run, "text2motion")
    if patch:
        res = subprocess.run(["git", "apply", PATCH], cwd=run, capture_output=True, text=True)
        assert res.returncode == 0, f"git apply {PATCH} failed:\n{res.stderr}"
    else:  # the hooks / launcher must work on untouched upstream files
        for rel in UPSTREAM_FILES:
            assert "smdm" not in open(os.path.join(t2m, rel)).read(), rel
    os.makedirs(os.path.join(t2m, "data"), exist_ok=True)
    os.symlink(DATA, os.path.join(t2m, "data", "HumanML3D"))
    return t2m


def _env(hooks: str = "", record: str = "", anomaly: bool = True) -> dict:
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""),
               SMDM_HOOKS=hooks, SMDM_NO_PLOT="1", SMDM_CLIP_LAYERS="2", SMDM_SEED="0",
               PYTHONUNBUFFERED="1")
    for k in ("SMDM_RECORD", "SMDM_NO_ANOMALY"):
        env.pop(k, None)
    if record:
        env["SMDM_RECORD"] = record
    if not anomaly:  # upstream's tools/train.py turns on autograd anomaly detection: slow on CPU
        env["SMDM_NO_ANOMALY"] = "1"
    return env


def _run(cmd, cwd, env, timeout=900) -> str:
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"{' '.join(cmd)}\n--- output tail ---\n{out[-6000:]}"
    return out


def harness(cwd, *argv, hooks="", record="", anomaly=True):
    return _run([sys.executable, os.path.join(HERE, "upstream_harness.py"), cwd, *argv], cwd,
                _env(hooks, record, anomaly))


def train_args(times: int) -> list:
    # one epoch over `times` copies of the 63 training motions: 7 * times iterations of 8
    return ["tools/train.py", "--name", "sparse_ci", "--gpu_id", "0", "--batch_size", "8",
            "--num_layers", "2", "--latent_dim", "64", "--num_epochs", "1", "--times", str(times),
            "--lr", "1e-3", "--diffusion_steps", str(STEPS), "--log_every", "1",
            "--save_latest", "4", "--dataset_name", "t2m", "--sparse",
            "--sparse_reduction", str(REDUCTION)]


def load_records(path: str, kind: str):
    with open(path, "rb") as f:
        return [r for r in pickle.load(f) if r["kind"] == kind]


def check_masks(records, lo: float, hi: float) -> None:
    density = []
    for r in records:
        for row, L in zip(r["mask"], r["lengths"]):
            assert not row[L:].any() and row[:L].sum() >= 2
            density.append(row[:L].mean())
    assert lo < np.mean(density) < hi and max(density) < 0.6, (np.mean(density), max(density))


def check_blocks(record: str, calls: int) -> None:
    """Every model call sent only its keyframe tokens through the decoder blocks."""
    blocks = load_records(record, "blocks")
    assert len(blocks) == calls, (len(blocks), calls)
    for r in blocks:
        # static shapes: the blocks run on the schedule's capacity (>= every row's keyframes)
        assert r["mask"] is not None and r["tokens"] >= r["mask"].sum(1).max(), r["tokens"]
        assert r["tokens"] < 0.6 * r["mask"].shape[1], (r["tokens"], r["mask"].shape)


def check_training(t2m: str, out: str, record: str) -> np.ndarray:
    import torch

    save = os.path.join(t2m, "checkpoints", "t2m", "sparse_ci")
    opt = dict(l.strip().split(": ", 1) for l in open(os.path.join(save, "opt.txt")) if ": " in l)
    assert opt["sparse"] == "True" and float(opt["sparse_reduction"]) == REDUCTION, opt
    cfg = json.load(open(os.path.join(save, "model", "sparse_config.json")))
    assert cfg["enabled"] is True and cfg["reduction"] == REDUCTION, cfg
    # opt.txt states what ran: no FSQ keys (MotionDiffuse's default: its attention is linear; no
    # warning about it), the diffusion steps come from the diffusion
    assert opt["sparse_fsq"] == str(cfg["fsq"]) == "False" and cfg["fsq"] is False, (opt, cfg)
    assert opt["sparse_diffusion_steps"] == str(cfg["diffusion_steps"]), (opt, cfg)
    assert "fsq=True cannot apply" not in out, out[-3000:]
    assert "smdm: sparse keyframe mode ON (MotionDiffuse, training): " in out, out[-3000:]
    sd = torch.load(os.path.join(save, "model", "latest.tar"), map_location="cpu")["encoder"]
    assert "smdm_sparse_version" in sd and any(k.startswith("joint_embed.net.") for k in sd)

    losses = np.array([float(v) for v in re.findall(r"loss_mot_rec: (\S+)", out)])
    iters = int(re.findall(r"niter:\s+(\d+)", out)[-1])
    assert len(losses) == iters and np.isfinite(losses).all(), (iters, losses)
    trains = load_records(record, "train")
    assert len(trains) == iters, (len(trains), iters)  # a keyframe mask at every iteration
    check_masks(trains, 0.5 * (1 - REDUCTION), 2 * (1 - REDUCTION))
    check_blocks(record, iters)
    for tr, bl in zip(trains, load_records(record, "blocks")):  # the selected mask was used
        assert np.array_equal(tr["mask"] & (np.arange(tr["mask"].shape[1]) < tr["lengths"][:, None]),
                              bl["mask"])
    print("losses", np.round(losses, 4).tolist())
    return losses


def generate(t2m: str, tmp_path, hooks: str = "") -> None:
    npy, rec = str(tmp_path / "sample.npy"), str(tmp_path / "generate.pkl")
    harness(t2m, "tools/visualization.py", "--opt_path", "checkpoints/t2m/sparse_ci/opt.txt",
            "--text", "a person walks forward", "--motion_length", str(FRAMES),
            "--result_path", str(tmp_path / "s.gif"), "--npy_path", npy, hooks=hooks, record=rec)
    joints = np.load(npy)
    assert joints.shape == (FRAMES, 22, 3) and np.isfinite(joints).all() and joints.std() > 0
    samples = load_records(rec, "sample")
    assert len(samples) == STEPS and all(r["mask"].shape == (1, FRAMES) for r in samples)
    check_masks(samples, 0.5 * (1 - REDUCTION), 2 * (1 - REDUCTION))
    check_blocks(rec, STEPS)


def test_patch_train_and_generate(tmp_path):
    t2m = prepare(str(tmp_path / "MotionDiffuse"))
    rec = str(tmp_path / "train.pkl")
    out = harness(t2m, *train_args(2), record=rec, anomaly=False)  # 15 iterations
    losses = check_training(t2m, out, rec)
    assert len(losses) >= 14 and losses[-5:].mean() < 0.97 * losses[:5].mean(), losses
    generate(t2m, tmp_path)


def test_hooks_train_and_generate(tmp_path):
    """``install_hooks()`` (what ``smdm run`` installs) on an unpatched checkout; upstream's
    visualization.py has no --sparse flag: the config comes from the checkpoint's opt.txt /
    sparse_config.json."""
    t2m = prepare(str(tmp_path / "MotionDiffuse"), patch=False)
    rec = str(tmp_path / "train.pkl")
    out = harness(t2m, *train_args(1), hooks="motiondiffuse", record=rec)
    check_training(t2m, out, rec)
    generate(t2m, tmp_path, hooks="motiondiffuse")


def test_launcher_train(tmp_path):
    """``smdm run --repo COPY/text2motion --integration motiondiffuse -- python HARNESS ...
    tools/train.py ... --sparse``: the hooks come from the launcher's sitecustomize (the harness
    installs none; it only stubs what this machine lacks)."""
    t2m = prepare(str(tmp_path / "MotionDiffuse"), patch=False)
    rec = str(tmp_path / "train.pkl")
    cmd = LAUNCHER + ["--repo", t2m, "--integration", "motiondiffuse", "--",
                             sys.executable, os.path.join(HERE, "upstream_harness.py"), t2m,
                             *train_args(1)]
    out = _run(cmd, REPO, _env(record=rec))
    check_training(t2m, out, rec)


@pytest.mark.parametrize("batch,frames", [(1, 40), (32, 196), (7, 60)])
def test_the_flag_s_mask_is_the_checkout_s(batch, frames):
    """``families/motiondiffuse/upstream_loop.src_mask`` against this checkout's own
    ``MotionTransformer.generate_src_mask`` (``scripts/time_src_mask.py`` reads it from the file and
    exits 1 when the two differ), and the script's table."""
    script = os.path.join(REPO, "scripts", "time_src_mask.py")
    out = _run([sys.executable, script, "--repo", ROOT, "--batch", str(batch), "--frames", str(frames),
                "--repeats", "3"], REPO, _env())
    assert f"B = {batch}, T = {frames}" in out and "| upstream's `generate_src_mask` |" in out, out
