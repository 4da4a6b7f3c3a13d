"""Keyframe-conditioned in-betweening: imputation in SimpleDiffusion (against step-by-step
reference loops), forced keyframes of sparse models, the policies, MDM's edit hook, the model
folders and representations, and ``smdm inbetween`` as a user runs it."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import types

import numpy as np
import pytest
import torch

from smdm_plugin.adapters.request import KEYFRAMES_KEY
from smdm_plugin.adapters import inbetween_sampling as ib
from smdm_plugin.adapters.surgery import sparsify
from smdm_plugin.adapters.state import get_state
from smdm_plugin.core.config import SparseConfig
from smdm_plugin.reference.backbone import TinyMDM
from smdm_plugin.reference.simple_diffusion import ClassifierFreeGuidance, SimpleDiffusion

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
D, N = 12, 24


def tiny(sparse: bool = False, cond_mode: str = "no_cond", steps: int = 8, D: int = D):
    torch.manual_seed(0)
    model = TinyMDM(njoints=D, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, num_heads=4,
                    cond_mode=cond_mode, clip_dim=16, dropout=0.0).eval()
    diffusion = SimpleDiffusion(steps)
    if sparse:
        sparsify(model, SparseConfig(reduction=0.8, feature="raw"), diffusion=diffusion)
    return model, diffusion


# --------------------------------------------------------------------------- reference loops
def reference_loop(diffusion, model, shape, y, gen, imputation=None):
    """The sampling loop written out step by step (the pre-imputation SimpleDiffusion when
    ``imputation`` is None; MDM's x0 replacement and/or x_t replacement otherwise)."""
    x = torch.randn(shape, generator=gen)
    mask = target = None
    if imputation:
        mask, target = y["inpainting_mask"].expand(shape), y["inpainted_motion"]
    abar = diffusion.abar
    for t in range(diffusion.num_timesteps - 1, -1, -1):
        tt = torch.full((shape[0],), t, dtype=torch.long)
        if imputation in ("xt", "both"):
            noise = torch.randn(shape, generator=gen)
            noised = abar[t].sqrt().float() * target + (1 - abar[t]).sqrt().float() * noise
            x = torch.where(mask, noised, x)
        x0 = model(x, tt, y)
        if imputation in ("x0", "both") or (imputation == "xt" and t == 0):
            x0 = torch.where(mask, target, x0)
        if t == 0:
            return x0
        mean = diffusion.coef_x0[t].float() * x0 + diffusion.coef_xt[t].float() * x
        x = mean + diffusion.post_var[t].sqrt().float() * torch.randn(shape, generator=gen)


def constraint_y(B=2, lengths=None, frames=(0, 7, 15, 23)):
    g = torch.Generator().manual_seed(1)
    target = torch.randn(B, N, D, generator=g)
    c = ib.keyframe_constraint(target, list(frames), lengths)
    return c, ib.conditioning(c, D, 1)


def test_no_constraint_is_bit_for_bit_the_plain_loop():
    for sparse in (False, True):
        model, diffusion = tiny(sparse)
        y = {"mask": torch.ones(2, 1, 1, N, dtype=torch.bool)}
        out = diffusion.p_sample_loop(model, (2, D, 1, N), {"y": y}, generator=torch.Generator().manual_seed(3))
        ref = reference_loop(diffusion, model, (2, D, 1, N), y, torch.Generator().manual_seed(3))
        assert torch.equal(out, ref)


@pytest.mark.parametrize("imputation", ["x0", "xt"])
@pytest.mark.parametrize("sparse", [False, True])
def test_imputation_matches_the_reference_loop_and_keyframes_are_exact(imputation, sparse):
    model, diffusion = tiny(sparse)
    c, y = constraint_y()
    out = diffusion.p_sample_loop(model, (2, D, 1, N), {"y": y}, generator=torch.Generator().manual_seed(5),
                                  imputation=imputation)
    ref = reference_loop(diffusion, model, (2, D, 1, N), y, torch.Generator().manual_seed(5), imputation)
    assert torch.allclose(out, ref, atol=1e-6, rtol=0)
    frames = ib.to_batch_major(out)
    given = c.frames
    assert torch.equal(frames[given], c.target[given])      # the given frames come out exact
    assert not torch.allclose(frames[~given], c.target[~given])


def test_replacing_the_prediction_too_changes_nothing_after_xt_imputation():
    """Why there is no "both": the posterior step is per entry, so a replaced prediction only changes
    the given entries of x_{t-1}, which the next x_t replacement overwrites."""
    model, diffusion = tiny(sparse=True)
    _, y = constraint_y()
    outs = [reference_loop(diffusion, model, (2, D, 1, N), y, torch.Generator().manual_seed(5), mode)
            for mode in ("xt", "both")]
    assert torch.allclose(outs[0], outs[1], atol=1e-6, rtol=0)


def test_sparse_model_keeps_the_forced_keyframes_as_tokens_at_every_step():
    model, diffusion = tiny(sparse=True, steps=6)
    seen = []
    model.register_forward_pre_hook(lambda m, a, k: seen.append(get_state(m).plan.mask.clone()),
                                    with_kwargs=True)
    lengths = torch.tensor([N, 17])
    c, y = constraint_y(lengths=lengths, frames=(0, 5, 9, 16))
    out = ib.sample_inbetween(model, diffusion, c, generator=torch.Generator().manual_seed(0))
    assert out.shape == (2, N, D) and len(seen) == 6
    for mask in seen:
        assert mask[c.frames].all()                                   # forced frames are tokens
        assert not mask[1, 17:].any()                                 # nothing beyond the length
    assert torch.equal(out[c.frames], c.target[c.frames])


def test_dense_and_sparse_with_text_and_guidance_keep_keyframes_and_leave_y_alone():
    for sparse in (False, True):
        model, diffusion = tiny(sparse, cond_mode="text")
        guided = ClassifierFreeGuidance(model, 2.5)
        c, _ = constraint_y(B=3, lengths=[N, 20, 12], frames=(0, 11))
        y = {"text_embed": torch.randn(3, 16)}
        out = ib.sample_inbetween(guided, diffusion, c, y=y, imputation="xt",
                                  generator=torch.Generator().manual_seed(0))
        assert set(y) == {"text_embed"}
        assert out.shape == (3, N, D) and torch.isfinite(out).all()
        assert torch.equal(out[c.frames], c.target[c.frames])


def brute_force_policy(frames, lengths, policy):
    out = torch.zeros_like(frames)
    for b in range(frames.shape[0]):
        L = int(lengths[b])
        for n in range(L):
            if not frames[b, n] or policy == "none":
                continue
            prev_given = n > 0 and bool(frames[b, n - 1])
            next_given = n + 1 < L and bool(frames[b, n + 1])
            out[b, n] = policy == "all" or not (prev_given and next_given)
    return out


@pytest.mark.parametrize("policy", ib.POLICIES)
def test_forced_policies_match_a_brute_force_reference(policy):
    g = torch.Generator().manual_seed(0)
    frames = torch.rand(16, 30, generator=g) < 0.5
    lengths = torch.randint(2, 31, (16,), generator=g)
    assert torch.equal(ib.forced_keyframes(frames, lengths, policy), brute_force_policy(frames, lengths, policy))


def test_mdm_in_between_mask_gives_prefix_suffix_and_ends_policy_picks_the_seams():
    B, L = 2, torch.tensor([40, 30])
    mask = torch.ones(B, D, 1, N + 16, dtype=torch.bool)
    for i, length in enumerate(L.tolist()):  # MDM's sample.edit: prefix 25%, suffix from 75%
        mask[i, :, :, int(0.25 * length):int(0.75 * length)] = False
    frames = ib.frames_from_inpainting_mask(mask, mask.shape)
    forced = ib.forced_keyframes(frames, L, "ends")
    assert forced[0].nonzero().flatten().tolist() == [0, 9, 30, 39]
    assert forced[1].nonzero().flatten().tolist() == [0, 6, 22, 29]
    upper_body = torch.zeros(1, D, 1, 1, dtype=torch.bool)
    upper_body[:, :5] = True  # channels of every frame, no whole frame
    assert not ib.frames_from_inpainting_mask(upper_body, (B, D, 1, N)).any()


def test_constraint_validation_messages():
    x = torch.zeros(2, N, D)
    with pytest.raises(ValueError, match=r"given frame indices must be in \[0, N=24\)"):
        ib.keyframe_constraint(x, [0, 24])
    with pytest.raises(ValueError, match="beyond its length 10"):
        ib.keyframe_constraint(x, [0, 12], lengths=[24, 10])
    with pytest.raises(ValueError, match="sample 1 has no given frame"):
        ib.keyframe_constraint(x, torch.tensor([[True] + [False] * 23, [False] * 24]))
    with pytest.raises(ValueError, match="NaN or inf"):
        ib.keyframe_constraint(torch.full((2, N, D), float("nan")), [3])
    with pytest.raises(ValueError, match=r"target must be a float motion \[B, N, D\]"):
        ib.keyframe_constraint(torch.zeros(N), [0])
    with pytest.raises(ValueError, match=r"lengths must be <= N=24, got max 30"):
        ib.keyframe_constraint(x, [0], lengths=[30, 4])
    with pytest.raises(ValueError, match="policy must be one of"):
        ib.forced_keyframes(torch.zeros(1, 4, dtype=torch.bool), policy="some")
    channels = torch.zeros(2, N, D, dtype=torch.bool)
    channels[:, 4, :3] = True  # the root channels of one frame only: imposed, not a whole keyframe
    c = ib.keyframe_constraint(x, channels)
    assert not c.frames.any() and c.given.sum() == 6


def test_mdm_style_diffusion_gets_the_inpainting_keys_and_xt_is_refused():
    calls = {}

    class MDMLikeDiffusion:  # MDM's GaussianDiffusion.p_sample_loop signature, no imputation=
        def p_sample_loop(self, model, shape, noise=None, clip_denoised=True, model_kwargs=None, progress=False):
            calls.update(shape=shape, clip=clip_denoised, y=model_kwargs["y"])
            return model_kwargs["y"]["inpainted_motion"].clone()

    model, _ = tiny(sparse=True)
    c, _ = constraint_y()
    out = ib.sample_inbetween(model, MDMLikeDiffusion(), c)
    assert calls["shape"] == (2, D, 1, N) and calls["clip"] is False
    assert calls["y"]["inpainting_mask"].shape == (2, D, 1, N) and calls["y"][KEYFRAMES_KEY].forced.shape == (2, N)
    assert torch.equal(out, c.target)
    with pytest.raises(ValueError, match="imputes the clean prediction only"):
        ib.sample_inbetween(model, MDMLikeDiffusion(), c, imputation="xt")


# --------------------------------------------------------------------------- MDM's sample.edit hook
def test_mdm_edit_hook_forces_the_kept_frames_of_a_sparse_model_only(monkeypatch):
    from smdm_plugin.families.mdm import upstream_edit as mdm_edit

    seen = {}

    class GaussianDiffusion:  # the part of MDM's diffusion the hook wraps
        def p_sample_loop(self, model, shape, noise=None, clip_denoised=True, model_kwargs=None, progress=False):
            seen["y"] = model_kwargs["y"]
            return shape

    fake = types.ModuleType("diffusion.gaussian_diffusion")
    fake.GaussianDiffusion = GaussianDiffusion
    monkeypatch.setitem(sys.modules, "diffusion.gaussian_diffusion", fake)
    mdm_edit.install_hooks()
    mdm_edit.install_hooks()  # idempotent
    assert GaussianDiffusion.p_sample_loop._smdm_wrapped

    mask = torch.ones(2, D, 1, N, dtype=torch.bool)
    mask[..., 6:18] = False
    y = {"inpainting_mask": mask, "inpainted_motion": torch.zeros(2, D, 1, N), "lengths": torch.tensor([N, 20])}
    sparse, _ = tiny(sparse=True)
    GaussianDiffusion().p_sample_loop(ClassifierFreeGuidance(sparse), (2, D, 1, N), clip_denoised=False,
                                      model_kwargs={"y": y})
    assert KEYFRAMES_KEY not in y  # the caller's dict is untouched
    assert seen["y"][KEYFRAMES_KEY].forced[0].nonzero().flatten().tolist() == [0, 5, 18, 23]
    assert seen["y"][KEYFRAMES_KEY].forced[1].nonzero().flatten().tolist() == [0, 5, 18, 19]
    dense, _ = tiny(sparse=False)
    GaussianDiffusion().p_sample_loop(dense, (2, D, 1, N), None, False, {"y": y})  # positional
    assert KEYFRAMES_KEY not in seen["y"]
    monkeypatch.setenv("SMDM_EDIT_FORCED", "all")
    kw = {"y": dict(y)}
    mdm_edit.add_forced_keyframes(sparse, kw)
    assert kw["y"][KEYFRAMES_KEY].forced.sum().item() == 12 + 8
    monkeypatch.setenv("SMDM_EDIT_FORCED", "every")
    with pytest.raises(ValueError, match="SMDM_EDIT_FORCED='every'"):
        mdm_edit.forced_for_edit(sparse, {"y": y})


# --------------------------------------------------------------------------- representation, folders
def test_joints66_round_trip_on_real_joints(hml_dir):
    from smdm_plugin.io.representation import Representation, canonical_xz, joints_to_joints66

    j = np.load(hml_dir / "new_joints" / "000003.npy")
    rep = Representation("joints66")
    f = rep.from_joints(j)
    assert f.shape == (len(j), 66) and np.allclose(f[:, 63], j[:, 0, 1])
    assert np.allclose(rep.to_joints(f), j, atol=1e-6)
    t = torch.from_numpy(j).double()
    assert torch.allclose(rep.to_joints(joints_to_joints66(t)), t)
    c = canonical_xz(j, 10)
    assert np.allclose(c[10, 0, [0, 2]], 0) and np.allclose(c[..., 1], j[..., 1])
    with pytest.raises(ValueError, match="cannot be computed from joint positions"):
        Representation("humanml3d").from_joints(j)
    with pytest.raises(ValueError, match="must be one of"):
        Representation("smpl")


def test_model_folder_round_trip_samples_the_same(tmp_path):
    from smdm_plugin.training.bundle import load_bundle, save_bundle
    from smdm_plugin.io.files import OutputExistsError
    from smdm_plugin.io.representation import Representation

    rep = Representation("joints66")
    model, diffusion = tiny(sparse=True, D=66)
    kw = dict(njoints=66, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, num_heads=4, cond_mode="no_cond",
              clip_dim=16, dropout=0.0)
    mean, std = np.random.default_rng(0).normal(size=66), np.full(66, 2.0)
    save_bundle(str(tmp_path / "m"), model, diffusion, kw, rep, mean, std, max_frames=N)
    with pytest.raises(OutputExistsError):
        save_bundle(str(tmp_path / "m"), model, diffusion, kw, rep, mean, std)
    b = load_bundle(str(tmp_path / "m"))
    assert b.sparse and b.config.reduction == 0.8 and b.max_frames == N and b.label == "sparse (80% dropped)"
    c = ib.keyframe_constraint(torch.randn(1, N, 66), [0, 10, 23])
    outs = [ib.sample_inbetween(m, diffusion, c, generator=torch.Generator().manual_seed(0))
            for m in (model, b.model)]
    assert torch.equal(outs[0], outs[1])
    x = torch.randn(3, 66, dtype=torch.float64)
    assert torch.allclose(b.denormalise(b.normalise(x)), x)
    with pytest.raises(FileNotFoundError, match="not a model folder"):
        load_bundle(str(tmp_path))


def test_plan_keyframes():
    from smdm_plugin.apps.common.bundle_inbetween import plan_keyframes

    kf = plan_keyframes(200, [30, 60, 90], None, None, None, 196)
    assert (kf.frames, kf.start, kf.length, kf.placed) == ([0, 30, 60], 30, 61, False)
    kf = plan_keyframes(3, [0, 50, 99], None, None, None, 196)  # three poses placed at frames
    assert (kf.frames, kf.source_frames, kf.length, kf.placed) == ([0, 50, 99], [0, 1, 2], 100, True)
    kf = plan_keyframes(100, None, 20, 10, None, 196)
    assert kf.frames == [0, 20, 40, 60, 80, 89] and kf.source_frames[0] == 10 and kf.length == 90
    for args, msg in (((100, [5, 120], None, None, None, 196), "beyond the 100 frames"),
                      ((300, [0, 250], None, None, None, 196), "exceeds the 196 frames"),
                      ((100, [10, 20], None, 15, None, 196), "after the first keyframe"),
                      ((100, [10, 20], None, None, 5, 196), "too short"),
                      # what the other options leave (0.10.5: "--length must be >= 2, got 1", none given)
                      ((58, None, None, 57, None, 196), "--start 57 leaves 1 frame of the 58-frame keyframe file"),
                      ((58, [5], None, None, None, 196), r"--frames \[5\] from --start 5 span 1 frame"),
                      ((58, None, None, 10, 1, 196), "--length must be >= 2, got 1")):
        with pytest.raises(ValueError, match=msg):
            plan_keyframes(*args)


# --------------------------------------------------------------------------- real held-out clips
def test_given_frames_exact_on_held_out_real_clips_dense_and_sparse(hml_dir):
    """HumanML3D features of the val split, normalised as MDM does, variable lengths padded to 196."""
    mean, std = np.load(hml_dir / "Mean.npy"), np.load(hml_dir / "Std.npy")
    ids = (hml_dir / "val.txt").read_text().split()[:4]
    motions = [np.load(hml_dir / "new_joint_vecs" / f"{i}.npy") for i in ids]
    Nf = 196
    x = torch.zeros(len(ids), Nf, 263)
    given = torch.zeros(len(ids), Nf, dtype=torch.bool)
    for b, m in enumerate(motions):
        x[b, :len(m)] = torch.from_numpy((m - mean) / std).float()
        given[b, torch.arange(0, len(m), 20)] = True
        given[b, len(m) - 1] = True
    c = ib.keyframe_constraint(x, given, [len(m) for m in motions])
    for sparse in (False, True):
        torch.manual_seed(0)
        model = TinyMDM(njoints=263, latent_dim=32, ff_size=64, num_layers=1, cond_mode="no_cond").eval()
        diffusion = SimpleDiffusion(5)
        if sparse:
            sparsify(model, SparseConfig(), diffusion=diffusion, mean=mean, std=std)
        out = ib.sample_inbetween(model, diffusion, c, generator=torch.Generator().manual_seed(0))
        assert out.shape == (len(ids), Nf, 263)
        assert torch.equal(out[given], x[given])


# --------------------------------------------------------------------------- the command
def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "smdm_plugin", "inbetween", *args], capture_output=True,
                          text=True, cwd=cwd, timeout=600)


@pytest.fixture(scope="module")
def model_folders(tmp_path_factory):
    from smdm_plugin.training.bundle import save_bundle
    from smdm_plugin.io.representation import Representation

    root = tmp_path_factory.mktemp("models")
    for rep in ("joints66", "humanml3d"):
        dim = Representation(rep).dim
        kw = dict(njoints=dim, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, num_heads=4,
                  cond_mode="no_cond", dropout=0.0)
        for name in ("dense", "sparse"):
            torch.manual_seed(0)
            model, diffusion = TinyMDM(**kw), SimpleDiffusion(4)
            if name == "sparse":
                sparsify(model, SparseConfig(feature="raw"), diffusion=diffusion)
            save_bundle(str(root / f"{rep}-{name}"), model, diffusion, kw, Representation(rep),
                        np.zeros(dim), np.ones(dim) * 0.5)
    return root


def test_cli_bvh_keyframes_dense_and_sparse(model_folders, tmp_path, mocap_files):
    from PIL import Image

    from smdm_plugin.apps.common.keyframe_study import find_bvh
    from smdm_plugin.io.bvh import load_cmu_clip

    files = find_bvh([os.path.dirname(mocap_files[0])])
    if not files:
        pytest.skip("no CMU BVH clip available")
    out = tmp_path / "ib"
    p = run("--model", str(model_folders / "joints66-dense"), str(model_folders / "joints66-sparse"),
            "--keyframes", files[0], "--frames", "5", "20", "35", "--samples", "2", "--out", str(out), "--quiet")
    assert p.returncode == 0, p.stderr
    kf = json.loads((out / "keyframes.json").read_text())
    assert kf["frames"] == [0, 15, 30] and kf["length"] == 31
    joints = load_cmu_clip(files[0])[5:36]
    for name in ("joints66-dense", "joints66-sparse"):
        out_j = np.load(out / f"{name}_joints.npy")
        assert out_j.shape == (2, 31, 22, 3)
        assert np.abs(out_j[:, [0, 15, 30]] - joints[[0, 15, 30]]).max() < 1e-5  # exact, global position too
    rows = json.loads((out / "summary.json").read_text())["rows"]
    assert all(r["keyframe_error_mm"] < 0.01 for r in rows) and "sparse (80% dropped)" in rows[1]["model"]
    assert Image.open(out / "inbetween.gif").n_frames == 31
    # the folder is not overwritten without --overwrite, and nothing in it changes
    before = (out / "summary.md").read_bytes()
    p = run("--model", str(model_folders / "joints66-dense"), "--keyframes", files[0], "--out", str(out))
    assert p.returncode == 2 and "--overwrite" in p.stderr and "Traceback" not in p.stderr
    assert (out / "summary.md").read_bytes() == before


def test_cli_humanml3d_features_and_clear_errors(model_folders, hml_dir, tmp_path, capsys):
    from smdm_plugin.apps import inbetween as cli

    feats = hml_dir / "new_joint_vecs" / "000003.npy"
    out = tmp_path / "h"
    assert cli.main(["--model", str(model_folders / "humanml3d-sparse"), "--keyframes", str(feats), "--every", "30",
                     "--length", "61", "--no-gif", "--out", str(out), "--quiet"]) == 0
    f = np.load(out / "humanml3d-sparse_features.npy")
    src = np.load(feats)[:61]
    assert f.shape == (1, 61, 263) and np.abs(f[0, [0, 30, 60]] - src[[0, 30, 60]]).max() < 1e-5
    poses = np.load(hml_dir / "new_joints" / "000003.npy")[[0, 50, 100]]  # three poses placed at 0, 20, 39
    np.save(tmp_path / "poses.npy", poses)
    assert cli.main(["--model", str(model_folders / "joints66-sparse"), "--keyframes", str(tmp_path / "poses.npy"),
                     "--frames", "0", "20", "39", "--no-gif", "--out", str(tmp_path / "p"), "--quiet"]) == 0
    j = np.load(tmp_path / "p" / "joints66-sparse_joints.npy")
    assert j.shape == (1, 40, 22, 3) and np.abs(j[0, [0, 20, 39]] - poses).max() < 1e-5
    bad = [(["--model", str(model_folders / "humanml3d-dense"), "--keyframes", str(hml_dir / "new_joints" / "000003.npy")],
            "HumanML3D (263-D) model"),
           (["--model", str(model_folders / "joints66-dense"), "--keyframes", str(feats), "--frames", "5", "400"],
            "beyond the 144 frames"),
           (["--model", str(tmp_path), "--keyframes", str(feats)], "not a model folder"),
           (["--model", str(model_folders / "joints66-dense"), "--keyframes", str(feats), "--samples", "0"],
            "argument --samples"),
           (["--model", str(model_folders / "joints66-dense"), "--keyframes", str(feats), "--device", "cuda:7"],
            "argument --device"),
           (["--model", str(model_folders / "joints66-dense"), "--keyframes", str(feats), "--frames", "3", "--every", "2"],
            "give one of them"),
           (["--model", str(model_folders / "joints66-dense"), "--keyframes", str(tmp_path / "none.npy")],
            "no such file"),
           # which keyframes are a sparse model's tokens: with dense models only it cannot apply (0.10.5 ignored it)
           (["--model", str(model_folders / "humanml3d-dense"), "--keyframes", str(feats), "--forced", "all"],
            "--forced all: applies to sparse models only")]
    for args, msg in bad:
        with pytest.raises(SystemExit) as e:
            cli.main([*args, "--out", str(tmp_path / "never")])
        err = capsys.readouterr().err
        assert e.value.code == 2 and msg in err, (args, err)
        assert err.strip().splitlines()[-1].startswith("smdm inbetween: error")
    assert not (tmp_path / "never").exists()
    # as a user runs it: one line, exit 2, no traceback
    p = run("--model", str(model_folders / "humanml3d-dense"), "--keyframes", str(hml_dir / "new_joints" / "000003.npy"))
    assert p.returncode == 2 and "Traceback" not in p.stderr and "HumanML3D (263-D) model" in p.stderr


def test_transition_frames_and_metrics_known_answers(hml_dir):
    from smdm_plugin.metrics.inbetween_metrics import keyframe_metrics, transition_frames
    from smdm_plugin.metrics import jitter

    given = torch.tensor([[1, 0, 0, 0, 1, 1, 1, 0, 0, 1]], dtype=torch.bool)
    assert transition_frames(given, torch.tensor([10]))[0].nonzero().flatten().tolist() == [0, 1, 3, 4, 6, 7, 8, 9]
    assert transition_frames(given, torch.tensor([6]))[0].nonzero().flatten().tolist() == [0, 1, 3, 4]
    j = np.load(hml_dir / "new_joints" / "000003.npy")[:60]
    g = np.zeros(60, bool)
    g[[0, 20, 40, 59]] = True
    m = keyframe_metrics(j[None], j, g, reference=True)
    assert m["keyframe_error_mm"] == 0 and m["inbetween_error_mm"] == 0
    assert m["jitter"] == pytest.approx(m["reference_jitter"]) == pytest.approx(float(jitter(j)))
    moved = j + np.array([0.1, 0, 0])  # 10 cm sideways: global error 100 mm, pose error 0
    m = keyframe_metrics(moved[None], j, g, reference=True)
    assert m["keyframe_error_mm"] == pytest.approx(100) and m["keyframe_error_root_relative_mm"] == pytest.approx(0, abs=1e-9)
    assert m["inbetween_error_mm"] == pytest.approx(100)
