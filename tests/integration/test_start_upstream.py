"""Start sparse from a dense checkpoint with the real upstream code (MDM through the patch and the
``smdm run`` launcher, priorMDM DoubleTake through the patch): a harness-sized DENSE checkpoint

* sampled sparse with ``--sparse_preset zero_shot`` (``sample.generate``, ``sample.double_take``):
  the output says that a dense checkpoint was wrapped, the samples are finite; with a preset at
  reduction 0 the wrapped samples equal the dense ones (every trained weight used as it is);
* warm-started into sparse training with ``--sparse_init_from`` (20 steps): ``args.json`` records
  the origin (path + sha256 of the dense file), and the sparse checkpoint samples with no flag.

Skipped unless ``SMDM_MDM_ROOT`` / ``SMDM_PRIORMDM_ROOT`` point at the checkouts (see
test_mdm_upstream.py / test_priormdm_upstream.py, whose helpers are used).
"""
from __future__ import annotations

import hashlib
import json
import os

import numpy as np
import pytest

import test_mdm_upstream as M
import test_priormdm_upstream as P

needs_mdm = pytest.mark.skipif(not M.ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")
needs_priormdm = pytest.mark.skipif(not P.ROOT, reason="SMDM_PRIORMDM_ROOT not set")
WRAPPED = "wrapped the DENSE checkpoint"


def sha256(path):
    with open(path, "rb") as f:
        return "sha256:" + hashlib.sha256(f.read()).hexdigest()


@pytest.fixture(scope="module")
def mdm_patched(upstream_copy):
    return upstream_copy(M.ROOT, "mdm_patched_start", patch=M.PATCH)


@pytest.fixture(scope="module")
def mdm_pristine(upstream_copy):
    return upstream_copy(M.ROOT, "mdm_pristine_start")


@pytest.fixture(scope="module")
def dense_mdm(mdm_patched, tmp_path_factory):
    save = str(tmp_path_factory.mktemp("runs") / "dense_enc")
    proc, ckpt = M.train(mdm_patched, save, "trans_enc", 6)
    assert json.load(open(os.path.join(save, "args.json")))["sparse"] is False
    return ckpt


@needs_mdm
@pytest.mark.parametrize("launcher", [False, True], ids=["patch", "launcher"])
def test_generate_wraps_a_dense_checkpoint(launcher, dense_mdm, mdm_patched, mdm_pristine, tmp_path):
    repo = mdm_pristine if launcher else mdm_patched
    proc, dense = M.generate(repo, dense_mdm, str(tmp_path / "dense"), "trans_enc", launcher=launcher)
    assert WRAPPED not in proc.stdout
    proc, wrapped = M.generate(repo, dense_mdm, str(tmp_path / "wrapped"), "trans_enc",
                               ["--sparse_preset", "zero_shot"], launcher=launcher)
    assert WRAPPED in proc.stdout and "zero_shot" in proc.stdout, proc.stdout[-2000:]
    on = [ln for ln in proc.stderr.splitlines() if "sparse keyframe mode ON" in ln]   # what the run does
    assert len(on) == 1 and on[0].startswith("smdm: sparse keyframe mode ON (MDM/DiP, sampling): "), proc.stderr[-2000:]
    assert "uniform keyframes at every step (dynamic update off), linear fill" in on[0]
    assert "vw" not in on[0] and "mask noise" not in on[0]
    cfg = json.load(open(os.path.join(str(tmp_path / "wrapped"), "sparse_config.json")))   # beside results.npy
    assert cfg["reduction"] == 0.8 and cfg["fsq"] is False and cfg["lipschitz"] is False
    assert not os.path.exists(os.path.join(str(tmp_path / "dense"), "sparse_config.json"))
    assert wrapped["motion"].shape == dense["motion"].shape and np.isfinite(wrapped["motion"]).all()
    assert not np.allclose(wrapped["motion"], dense["motion"], atol=1e-3)   # 80% of the frames dropped
    # a preset at reduction 0: the wrapped model computes the dense model's samples
    preset = tmp_path / "all_frames.yaml"
    preset.write_text("sparse: {reduction: 0.0, lipschitz: false, fsq: false}\n")
    proc, full = M.generate(repo, dense_mdm, str(tmp_path / "full"), "trans_enc", ["--sparse_preset", str(preset)],
                            launcher=launcher)
    assert WRAPPED in proc.stdout
    np.testing.assert_allclose(full["motion"], dense["motion"], atol=1e-4)


@needs_mdm
def test_preset_with_new_layers_is_refused_for_a_dense_checkpoint(dense_mdm, mdm_patched, tmp_path):
    proc, _ = M.generate(mdm_patched, dense_mdm, str(tmp_path / "x"), "trans_enc", ["--sparse_preset", "smdm_paper"],
                         check=False)
    assert proc.returncode != 0 and "no weights for" in proc.stdout + proc.stderr


@needs_mdm
def test_warm_start_trains_and_samples_with_no_flag(dense_mdm, mdm_patched, tmp_path):
    save = str(tmp_path / "warm")
    proc, ckpt = M.train(mdm_patched, save, "trans_enc", 20, ["--sparse", "--sparse_init_from", dense_mdm,
                                                               "--log_interval", "10"])
    out = proc.stdout + proc.stderr
    assert "initialised from the dense checkpoint" in out and "relative RMS error" in out, out[-2000:]
    args = json.load(open(os.path.join(save, "args.json")))
    assert args["sparse"] is True and args["sparse_init_origin"]["digest"] == sha256(dense_mdm)
    assert args["sparse_init_origin"]["path"] == os.path.abspath(dense_mdm)
    fits = args["sparse_init_origin"]["fit"]["mlps"]
    assert fits and all(f["rel_rms"] < 1e-2 for f in fits), fits
    assert os.path.isfile(os.path.join(save, "sparse_config.json"))
    assert "smdm_sparse_version" in M.load_sd(ckpt)
    proc, res = M.generate(mdm_patched, ckpt, str(tmp_path / "gen"), "trans_enc")   # no flag
    assert WRAPPED not in proc.stdout and "initialised" not in proc.stdout
    assert np.isfinite(res["motion"]).all() and res["motion"].shape == (2, 22, 3, 40)


@needs_priormdm
def test_double_take_wraps_a_dense_checkpoint(tmp_path):
    run = P.prepare(str(tmp_path / "priormdm"))
    save = os.path.join(run, "save", "dense")
    args = [a for a in P.train_args(save, 4) if a not in ("--sparse", "--sparse_reduction", str(P.REDUCTION))]
    P.harness(run, *args)
    ckpt = os.path.join(save, "model000000004.pt")
    texts = os.path.join(run, "dt_texts.txt")
    with open(texts, "w") as f:
        f.write("a person walks forward\na person jumps up and down\na person waves\n")
    out = P.harness(run, "-m", "sample.double_take", "--model_path", ckpt, "--num_samples", "3",
                    "--handshake_size", str(P.H), "--blend_len", str(P.BLEND), "--skip_steps_double_take",
                    str(P.SKIP), "--input_text", texts, "--guidance_param", "2.5", "--sparse_preset", "zero_shot")
    assert WRAPPED in out, out[-3000:]
    out_dir = P.dt_out_dir(run, ckpt, input_text=texts)
    motion = np.load(os.path.join(out_dir, "results.npy"), allow_pickle=True).item()["motion"]
    assert motion.shape == (1, 22, 3, 3 * P.SEG - 2 * P.H) and np.isfinite(motion).all()
    cfg = json.load(open(os.path.join(out_dir, "sparse_config.json")))   # what ran, beside the samples
    assert cfg["lipschitz"] is False and cfg["fsq"] is False and cfg["reduction"] == 0.8
