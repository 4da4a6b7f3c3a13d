"""The first hour with the commands (docs/first_hour.md): commands that connect (clips -> inbetween ->
render, train -> inbetween), one frame-index scale, outputs that say what they are. (Thread defaults:
tests/apps/test_threads.py.)"""
from __future__ import annotations

import json

import numpy as np
import pytest

from helpers.synthetic_data import write_humanml3d


# ----------------------------------------------------------------------------------------- clips
def test_clips_export_is_the_embedded_clip(tmp_path, monkeypatch, capsys):
    from smdm_plugin.apps import clips
    from smdm_plugin.apps.common.motion_files import load_motion
    from smdm_plugin.io.embedded import embedded_clips

    monkeypatch.chdir(tmp_path)
    assert clips.main([]) == 0 and "05_02" in capsys.readouterr().out
    assert clips.main(["export", "05_02"]) == 0
    ref = dict(embedded_clips())["05_02"]
    np.testing.assert_array_equal(np.load("05_02.npy"), ref)
    m = load_motion("05_02.npy")
    assert m.kind == "joints" and m.joints.shape == ref.shape
    assert clips.main(["export", "05_02", "--out", "f.npy", "--format", "joints66"]) == 0
    np.testing.assert_allclose(load_motion("f.npy").joints - load_motion("f.npy").joints[:, :1],
                               ref - ref[:, :1], atol=1e-5)  # the same pose, root-relative
    with pytest.raises(SystemExit):  # never over an existing file
        clips.main(["export", "05_02"])
    assert "--overwrite" in capsys.readouterr().err
    # --frames: those poses only, in the order given; a frame past the clip is an argparse error
    assert clips.main(["export", "05_02", "--frames", "100", "0", "40", "--out", "poses.npy"]) == 0
    np.testing.assert_array_equal(np.load("poses.npy"), ref[[100, 0, 40]])
    with pytest.raises(SystemExit) as e:
        clips.main(["export", "05_02", "--frames", str(len(ref)), "--out", "bad.npy"])
    assert e.value.code == 2 and f"has {len(ref)} frames" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------- connect
def test_render_reads_what_inbetween_writes(tmp_path):
    """`[S, N, D]` feature files (inbetween's *_features.npy) pick one sample, like joints files."""
    from smdm_plugin.apps.common.motion_files import load_motion
    from smdm_plugin.io.embedded import embedded_clips
    from smdm_plugin.io.representation import Representation

    j = dict(embedded_clips())["02_01"][:30]
    f = np.stack([Representation("joints66").from_joints(j), Representation("joints66").from_joints(j + 1.0)])
    np.save(tmp_path / "m_features.npy", f)
    m1 = load_motion(str(tmp_path / "m_features.npy"), sample=1)
    assert m1.kind == "joints66" and m1.features.shape == (30, 66)
    np.testing.assert_allclose(m1.joints, j + 1.0, atol=1e-5)
    with pytest.raises(ValueError, match="sample must be in"):
        load_motion(str(tmp_path / "m_features.npy"), sample=2)


def test_a_train_folder_is_a_model_inbetween_reads(tmp_path):
    from smdm_plugin.apps import inbetween
    from smdm_plugin.apps import train as trainer
    from smdm_plugin.training.trainer import load_trained
    from smdm_plugin.training.bundle import load_bundle

    data = write_humanml3d(tmp_path / "hml")
    out = tmp_path / "run"
    assert trainer.main(["--data", str(data), "--out", str(out), "--steps", "2", "--batch", "2",
                         "--latent-dim", "16", "--layers", "1", "--heads", "2", "--ff-size", "32",
                         "--diffusion-steps", "4", "--sparse", "--threads", "1", "--no-progress"]) == 0
    b = load_bundle(str(out))
    meta = json.loads((out / "motion.json").read_text())
    assert b.sparse and b.representation.name == "humanml3d" and b.diffusion.num_timesteps == 4
    assert meta["max_frames"] == 196 and np.allclose(meta["mean"], np.load(out / "Mean.npy"))
    model2, _ = load_trained(str(out))
    sd1, sd2 = b.model.state_dict(), model2.state_dict()
    assert all(np.array_equal(sd1[k].numpy(), sd2[k].numpy()) for k in sd1)
    keys = data / "new_joint_vecs" / "val000.npy"
    ib = tmp_path / "ib"
    assert inbetween.main(["--model", str(out), "--keyframes", str(keys), "--every", "10", "--out", str(ib),
                           "--no-gif", "--quiet", "--threads", "1"]) == 0
    feats = np.load(ib / "run_features.npy")
    kf = json.loads((ib / "keyframes.json").read_text())["frames"]
    np.testing.assert_allclose(feats[0, kf], np.load(keys)[kf], atol=1e-4)  # keyframes imposed


# ----------------------------------------------------------------------------------------- one scale
def test_one_frame_index_scale_default():
    from smdm_plugin import SparseConfig
    from smdm_plugin.apps import demo, keyframes

    lib = SparseConfig().frame_index_scale
    assert keyframes.build_parser().get_default("frame_index_scale") == lib
    p = __import__("argparse").ArgumentParser()
    demo.add_arguments(p)
    assert p.get_default("frame_index_scale") == lib
    from smdm_plugin.apps.common.keyframe_study import keyframe_study

    assert keyframe_study.__defaults__[-1] == lib


# ----------------------------------------------------------------------------------------- outputs
def test_quick_ablation_variants_are_distinct_and_record_what_ran():
    from smdm_plugin.apps import ablate
    from smdm_plugin.apps.ablate import grid

    cfg = grid.load_config("quick")
    resolved = [json.dumps(ablate.variant_settings(cfg, v)["sparse_config"], sort_keys=True) for v in cfg["variants"]]
    assert len(set(resolved)) == len(resolved), "two variants of the quick grid run the same model"
    for v in cfg["variants"]:
        sc = ablate.variant_settings(cfg, v)["sparse_config"]
        assert sc is None or sc["diffusion_steps"] == cfg["diffusion_steps"]


def test_ablate_without_data_says_which_data(tmp_path, monkeypatch, capsys):
    from smdm_plugin.apps import ablate

    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        ablate.main(["--config", "quick", "--out", "o"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--data" in err and "HumanML3D" in err and "smdm demo" in err
    assert not (tmp_path / "o").exists()


def test_bench_quick_leaves_targets_out():
    from smdm_plugin.apps import bench

    row = {"arch": "trans_enc", "mode": "train", "variant": "sparse 80%", "reduction": 0.8, "median_s": 0.01,
           "speedup": 1.0, "cpu_s": 0.01, "cpu_speedup": 1.0, "peak_mem_mib": 3.0, "mem_ratio": 0.1}
    res = {"amp": "fp32", "compile": "none", "device_name": "cpu", "device": "cpu", "torch": "x", "threads": 1,
           "sparse_backend": "varlen", "batch": 4, "frames": 60, "model": {}, "diffusion_steps": 50, "repeats": 1,
           "warmup": 0, "rows": [row]}
    full = bench.markdown(res)
    quick = bench.markdown({**res, "quick": True})
    assert "MISSED" in full and "| 0.10 |" in full
    assert "MISSED" not in quick and " met" not in quick and "| 0.10 |" not in quick
    assert "--quick:" in quick and "left out" in quick
