"""priorMDM end to end, with the patch, the import hooks and the ``smdm run`` launcher: train a
tiny sparse MDM on cmu-humanml3d with upstream's ``train.train_mdm``, save, and sample DoubleTake
from it with upstream's ``sample.double_take``.

Skipped unless ``SMDM_PRIORMDM_ROOT`` points at a priorMDM checkout (read-only; its committed
files are copied to a temporary directory). ``SMDM_HUMANML3D_DIR`` overrides the data (default
``shared/data/cmu-humanml3d`` beside the repo,).
Needs the upstream's Python deps (see docs/priormdm.md): blobfile, smplx, openai-clip (--no-deps),
ftfy, pandas, matplotlib, scipy, tqdm. CLIP weights are random and its text transformer has 2
layers (harness), SMPL files are not needed.

What is checked (each would fail if the integration were wrong):

* ``--sparse*`` are accepted by upstream's parser and land in ``args.json``;
* the checkpoint carries ``smdm_sparse_version`` and the Lipschitz layers;
* every training step selected a keyframe mask with about ``1 - reduction`` of the valid frames,
  none past a sequence's length, and handed it to the transformer; the loss is finite and goes
  down over 21 steps;
* DoubleTake: every model call (both takes, both classifier-free-guidance passes) ran on a sparse
  mask that holds the forced frames computed from the geometry
  (:func:`smdm_plugin.families.doubletake.model.doubletake_forced_frames`, independent of the
  ``y``-based hook under test); the unfolded sample is finite, ``[1, 22, 3, 3*150 - 2*10]``.
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
from _upstream import HERE, LAUNCHER, PATCHES, REPO, copy_checkout, find_humanml3d

ROOT = os.environ.get("SMDM_PRIORMDM_ROOT")
PATCH = os.path.join(PATCHES, "priormdm.patch")
DATA = find_humanml3d() or ""

pytestmark = [pytest.mark.skipif(not ROOT, reason="SMDM_PRIORMDM_ROOT not set"),
              pytest.mark.skipif(not DATA, reason="no HumanML3D-format data (SMDM_HUMANML3D_DIR)")]

H, BLEND, SKIP, DT_STEPS, SEG = 10, 5, 5, 20, 150  # DoubleTake geometry (n_frames=150 per prompt)
REDUCTION = 0.8


def make_glove(run: str, data: str) -> None:
    """A random word-vector table over the data's caption tokens (the T2M evaluator's GloVe
    cannot be downloaded; only its shape matters to the loaders)."""
    words = {"unk"}
    for f in os.listdir(os.path.join(data, "texts")):
        with open(os.path.join(data, "texts", f)) as fh:
            for line in fh:
                parts = line.strip().split("#")
                if len(parts) > 1:
                    words.update(t.split("/")[0] for t in parts[1].split(" ") if "/" in t)
    words = sorted(words)
    os.makedirs(os.path.join(run, "glove"), exist_ok=True)
    rng = np.random.default_rng(0)
    np.save(os.path.join(run, "glove", "our_vab_data.npy"),
            rng.standard_normal((len(words), 300)).astype(np.float32))
    with open(os.path.join(run, "glove", "our_vab_words.pkl"), "wb") as f:
        pickle.dump(words, f)
    with open(os.path.join(run, "glove", "our_vab_idx.pkl"), "wb") as f:
        pickle.dump({w: i for i, w in enumerate(words)}, f)


def prepare(run: str, patch: bool = True) -> str:
    copy_checkout(ROOT, run)
    if patch:
        res = subprocess.run(["git", "apply", PATCH], cwd=run, capture_output=True, text=True)
        assert res.returncode == 0, f"git apply {PATCH} failed:\n{res.stderr}"
    else:  # the hooks / launcher must work on untouched upstream files
        assert "smdm" not in open(os.path.join(run, "utils", "model_util.py")).read()
    os.makedirs(os.path.join(run, "dataset"), exist_ok=True)
    link = os.path.join(run, "dataset", "HumanML3D")
    if not os.path.exists(link):
        os.symlink(DATA, link)
    make_glove(run, DATA)
    return run


def _env(hooks: str = "", record: str = "") -> dict:
    env = dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""),
               DIFFUSION_TRAINING_TEST="1", SMDM_HOOKS=hooks, SMDM_NO_PLOT="1",
               SMDM_CLIP_LAYERS="2", PYTHONUNBUFFERED="1", WANDB_MODE="disabled")
    env.pop("SMDM_RECORD", None)
    if record:
        env["SMDM_RECORD"] = record
    return env


def _run(cmd, cwd, env, timeout=900) -> str:
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"{' '.join(cmd)}\n--- output tail ---\n{out[-6000:]}"
    return out


def harness(run: str, *argv: str, hooks: str = "", record: str = "") -> str:
    return _run([sys.executable, os.path.join(HERE, "upstream_harness.py"), run, *argv], run,
                _env(hooks, record))


def load_records(path: str, kind: str):
    with open(path, "rb") as f:
        return [r for r in pickle.load(f) if r["kind"] == kind]


def train_args(save: str, steps: int) -> list:
    # DIFFUSION_TRAINING_TEST=1: upstream's loop returns after the save at step `save_interval`
    return ["-m", "train.train_mdm", "--save_dir", save, "--dataset", "humanml", "--batch_size", "8",
            "--layers", "2", "--latent_dim", "64", "--diffusion_steps", str(DT_STEPS),
            "--num_steps", str(steps + 1), "--save_interval", str(steps), "--log_interval", "1",
            "--overwrite", "--lr", "1e-3", "--sparse", "--sparse_reduction", str(REDUCTION)]


def step_losses(out: str) -> np.ndarray:
    """Per-step losses from upstream's log: it prints the running mean of `loss` since the start
    (logkv_mean, never dumped), so loss_k = (k + 1) m_k - k m_{k-1}."""
    means = {int(k): float(v) for k, v in re.findall(r"step\[(\d+)\]: loss\[([^\]]+)\]", out)}
    m = np.array([means[k] for k in sorted(means)])
    assert len(m) > 0 and sorted(means) == list(range(len(m))), out[-3000:]
    k = np.arange(len(m))
    return np.concatenate([m[:1], (k[1:] + 1) * m[1:] - k[1:] * m[:-1]])


def check_training(save: str, out: str, record: str, steps: int) -> str:
    """args.json, checkpoint, keyframe masks of every step, loss; returns the last checkpoint."""
    import torch

    args = json.load(open(os.path.join(save, "args.json")))
    assert args["sparse"] is True and args["sparse_reduction"] == REDUCTION, args
    ckpts = sorted(f for f in os.listdir(save) if re.fullmatch(r"model\d+\.pt", f))
    assert ckpts and ckpts[-1] == f"model{steps:09d}.pt", (ckpts, out[-3000:])
    sd = torch.load(os.path.join(save, ckpts[-1]), map_location="cpu")
    assert "smdm_sparse_version" in sd
    assert any("poseEmbedding" in k and "parametrizations" in k for k in sd), list(sd)[:40]

    trains, fed = load_records(record, "train"), load_records(record, "transformer")
    assert len(trains) == steps + 1 and len(fed) == steps + 1, (len(trains), len(fed))
    density = []
    for tr, tf in zip(trains, fed):
        mask, lengths = tr["mask"], tr["lengths"]
        assert np.array_equal(mask, tf["mask"])  # what was selected is what the transformer got
        for row, L in zip(mask, lengths):
            assert not row[L:].any() and row[:L].sum() >= 2
            density.append(row[:L].mean())
    # 1 - reduction of the valid frames, up to mask noise and the selector's endpoints
    assert 0.5 * (1 - REDUCTION) < np.mean(density) < 2 * (1 - REDUCTION), np.mean(density)
    assert max(density) < 0.6, max(density)

    losses = step_losses(out)
    assert len(losses) == steps + 1 and np.isfinite(losses).all(), losses
    if steps >= 10:
        assert losses[-5:].mean() < 0.95 * losses[:5].mean(), losses
    return os.path.join(save, ckpts[-1])


def double_take(run: str, ckpt: str, hooks: str = "", record: str = "") -> np.ndarray:
    texts = os.path.join(run, "dt_texts.txt")
    with open(texts, "w") as f:
        f.write("a person walks forward\na person jumps up and down\na person waves\n")
    # (--output_dir disables --input_text in upstream's double_take.py: use the default dir)
    out = harness(run, "-m", "sample.double_take", "--model_path", ckpt, "--num_samples", "3",
                  "--handshake_size", str(H), "--blend_len", str(BLEND), "--skip_steps_double_take",
                  str(SKIP), "--input_text", texts, "--guidance_param", "2.5", hooks=hooks, record=record)
    assert "covers 196 frames" not in out and "y['mask'] covers" not in out, out[-3000:]  # no mask-length warning
    out_dir = dt_out_dir(run, ckpt, input_text=texts)
    check_files_agree(os.path.dirname(ckpt), out_dir)
    res = np.load(os.path.join(out_dir, "results.npy"), allow_pickle=True).item()
    motion = res["motion"]  # [1, 22, 3, T] joint positions of the unfolded sequence
    assert motion.shape == (1, 22, 3, 3 * SEG - 2 * H), motion.shape
    assert np.isfinite(motion).all() and motion.std() > 0
    return motion


def dt_out_dir(run: str, ckpt: str, seed: int = 10, input_text: str = "") -> str:
    """The folder sample.double_take wrote to, as the plugin derives it from upstream's options
    (the folder it writes sparse_config.json into); it must hold this run's results.npy."""
    import argparse

    from smdm_plugin.families.doubletake.upstream import doubletake_output_dir

    args = argparse.Namespace(model_path=ckpt, output_dir="", input_text=input_text, sample_gt=False,
                              double_take=True, seed=seed, handshake_size=H, blend_len=BLEND,
                              skip_steps_double_take=SKIP)
    cwd = os.getcwd()
    os.chdir(run)                              # upstream resolves a relative path from its folder
    try:
        out = doubletake_output_dir(args)
    finally:
        os.chdir(cwd)
    assert out and os.path.isfile(os.path.join(out, "results.npy")), out
    return out


def check_files_agree(save: str, out_dir: str) -> None:
    """The training run's ``args.json`` and ``sparse_config.json`` state the same sparse settings
    (every field, the ones set when the model was built included), and DoubleTake wrote the
    model's config beside its ``results.npy``."""
    from smdm_plugin import SparseConfig
    from smdm_plugin.core.agreement import disagreement

    saved = SparseConfig.load(os.path.join(save, "sparse_config.json"))
    args_file = os.path.join(save, "args.json")
    assert disagreement(saved, json.load(open(args_file)), "sparse_config.json", args_file,
                        ignore=("version",)) is None
    written = SparseConfig.load(os.path.join(out_dir, "sparse_config.json"))
    assert not written.differences(saved), written.differences(saved)


def check_forced(record: str) -> None:
    """Every model call of both takes got a sparse mask holding the forced frames."""
    from smdm_plugin.families.doubletake.model import doubletake_forced_frames

    lens = [SEG] * 3
    first = doubletake_forced_frames(lens, H, take="first").numpy()
    second = doubletake_forced_frames(lens, H, take="second", blend_len=BLEND).numpy()
    assert first.sum() == 4 * H and second.sum() == 2 * (H + 2 * BLEND)
    fed = load_records(record, "transformer")
    takes = {first.shape: (first, 0), second.shape: (second, 0)}
    for r in fed:
        m = r["mask"]
        assert m.shape in takes, m.shape
        forced, n = takes[m.shape]
        takes[m.shape] = (forced, n + 1)
        assert (m | ~forced).all(), "a DoubleTake forced frame was not a keyframe"
        assert m.mean() < 0.6, m.mean()  # still sparse
    # classifier-free guidance: 2 calls per step; first take all steps, second take skips SKIP
    assert takes[first.shape][1] == 2 * DT_STEPS, takes[first.shape][1]
    assert takes[second.shape][1] == 2 * (DT_STEPS - SKIP), takes[second.shape][1]


def test_patch_train_and_double_take(tmp_path):
    run, save = prepare(str(tmp_path / "priorMDM")), str(tmp_path / "save" / "sparse")
    rec = str(tmp_path / "train.pkl")
    out = harness(run, *train_args(save, 20), record=rec)
    ckpt = check_training(save, out, rec, 20)
    rec = str(tmp_path / "dt.pkl")
    motion = double_take(run, ckpt, record=rec)
    check_forced(rec)
    from smdm_plugin.metrics import doubletake_ees

    ees = doubletake_ees(np.transpose(motion, (0, 3, 1, 2)), [SEG] * 3, H)
    assert ees and all(np.isfinite(v) for v in ees.values()), ees
    print("EES", ees)


def test_hooks_train_and_double_take(tmp_path):
    """``install_hooks()`` (what ``smdm run`` installs) on an unpatched checkout; DoubleTake reads
    the sparse options back from ``args.json`` (a dense model would not load the checkpoint)."""
    run, save = prepare(str(tmp_path / "priorMDM"), patch=False), str(tmp_path / "save" / "hooks")
    rec = str(tmp_path / "train.pkl")
    out = harness(run, *train_args(save, 2), hooks="priormdm", record=rec)
    ckpt = check_training(save, out, rec, 2)
    rec = str(tmp_path / "dt.pkl")
    double_take(run, ckpt, hooks="priormdm", record=rec)
    check_forced(rec)


def test_launcher_train(tmp_path):
    """``smdm run --repo COPY -- python HARNESS COPY -m train.train_mdm ... --sparse``: the hooks
    come from the launcher's sitecustomize (the harness installs none; it only stubs CLIP's
    download and torchvision, which this machine lacks)."""
    run, save = prepare(str(tmp_path / "priorMDM"), patch=False), str(tmp_path / "save" / "run")
    rec = str(tmp_path / "train.pkl")
    cmd = LAUNCHER + ["--repo", run, "--", sys.executable,
                             os.path.join(HERE, "upstream_harness.py"), run, *train_args(save, 2)]
    out = _run(cmd, REPO, _env(record=rec))
    check_training(save, out, rec, 2)


def test_launcher_train_compiled_with_the_fused_optimizer_logs_each_step(tmp_path):
    """``--sparse_compile default`` where the fused optimizer applies (the CUDA policy standing in
    on the CPU): priorMDM's loop reads ``logger.get_current().name2val`` directly, never dumping,
    while the logger keeps its calls (``families/mdm/upstream_loop.py``): every step still prints
    its running loss mean, the run trains to its checkpoint, ``args.json`` says what applied."""
    from _upstream import fused_policy_path

    from smdm_plugin.families.mdm.upstream_optim import OPTIMIZER_NOTE

    run, save = prepare(str(tmp_path / "priorMDM"), patch=False), str(tmp_path / "save" / "run")
    rec = str(tmp_path / "train.pkl")
    cmd = LAUNCHER + ["--repo", run, "--", sys.executable, os.path.join(HERE, "upstream_harness.py"), run,
                      *train_args(save, 2), "--sparse_compile", "default"]
    env = _env(record=rec)
    env["SMDM_COMPILE_BACKEND"] = "aot_eager"
    env["PYTHONPATH"] = fused_policy_path(str(tmp_path / "site")) + os.pathsep + env["PYTHONPATH"]
    out = _run(cmd, REPO, env)
    check_training(save, out, rec, 2)
    losses = step_losses(out)
    assert len(losses) >= 2 and np.isfinite(losses).all(), out[-3000:]
    applied = json.load(open(os.path.join(save, "args.json")))["sparse_compile_applied"]
    assert applied.endswith("; " + OPTIMIZER_NOTE), applied


def test_sparse_double_take_draws_the_dense_prompts(tmp_path):
    """Same seed, prompts drawn from the dataset (no --input_text): a sparse DoubleTake samples the
    same prompts and lengths as a dense one (the plugin leaves upstream's RNG streams alone; the
    loader's shuffle is drawn after the model is built)."""
    run = prepare(str(tmp_path / "priorMDM"), patch=False)
    texts = {}
    for name, sparse in (("dense", False), ("sparse", True)):
        save = str(tmp_path / "save" / name)
        argv = train_args(save, 2)
        if not sparse:
            argv = argv[:argv.index("--sparse")]
        harness(run, *argv, hooks="priormdm")
        ckpt = os.path.join(save, "model000000002.pt")
        out = harness(run, "-m", "sample.double_take", "--model_path", ckpt, "--num_samples", "3",
                      "--handshake_size", str(H), "--blend_len", str(BLEND), "--skip_steps_double_take",
                      str(SKIP), "--guidance_param", "2.5", "--seed", "11", hooks="priormdm")
        assert "y['mask'] covers" not in out
        out_dir = dt_out_dir(run, ckpt, seed=11)
        res = np.load(os.path.join(out_dir, "results.npy"), allow_pickle=True).item()
        texts[name] = (list(res["text"]), [np.asarray(v).tolist() for v in res["lengths"]])
        assert os.path.exists(os.path.join(out_dir, "sparse_config.json")) == sparse
    assert texts["dense"] == texts["sparse"], texts
