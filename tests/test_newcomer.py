"""The newcomer's path (issue 22): thread defaults, commands that connect (clips -> inbetween ->
render, train -> inbetween), one frame-index scale, outputs that say what they are, messages."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from synthetic_data import write_humanml3d

ROOT = Path(__file__).resolve().parent.parent


# ----------------------------------------------------------------------------------------- threads
def test_default_threads_leaves_busy_cores_alone():
    from smdm_plugin.apps.common.threads import default_threads

    assert default_threads(cores=2, load=0.0, local_processes=1) == 2      # idle: every core
    assert default_threads(cores=2, load=2.0, local_processes=1) == 1      # two busy neighbours: one
    assert default_threads(cores=2, load=7.5, local_processes=1) == 1      # never below one
    assert default_threads(cores=16, load=4.2, local_processes=1) == 12    # round(16 - 4.2)
    assert default_threads(cores=16, load=0.0, local_processes=4) == 4     # torchrun: cores shared
    # the slow obvious reference: count the cores one by one while load remains
    for cores in range(1, 9):
        for load in np.arange(0, 10, 0.25):
            free = sum(1 for c in range(cores) if c + 0.5 <= cores - load)  # cores at least half idle
            assert default_threads(cores, float(load), 1) == max(1, free), (cores, load)


def test_choose_threads_order(monkeypatch):
    from smdm_plugin.apps.common.threads import choose_threads

    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert choose_threads(5) == (5, "--threads")
    assert choose_threads(None) == (3, "OMP_NUM_THREADS")
    monkeypatch.delenv("OMP_NUM_THREADS")
    n, why = choose_threads(None)
    assert n >= 1 and why.startswith("auto")


def test_cli_sets_passive_wait_policy_before_torch_loads(tmp_path):
    """In a fresh process, `smdm <cmd>` puts OMP_WAIT_POLICY=PASSIVE into the environment before
    torch is imported (and keeps a value the user set)."""
    code = ("import os, sys; from smdm_plugin.apps import cli; "
            "cli.COMMANDS['probe'] = ('probe_mod', ''); "
            "import types; m = types.ModuleType('probe_mod'); "
            "m.main = lambda argv: print(os.environ.get('OMP_WAIT_POLICY'), 'torch' in sys.modules) or 0; "
            "sys.modules['probe_mod'] = m; sys.exit(cli.main(['probe']))")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("OMP_WAIT_POLICY", None)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.stdout.split() == ["PASSIVE", "False"], out.stderr
    env["OMP_WAIT_POLICY"] = "ACTIVE"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.stdout.split()[0] == "ACTIVE"


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


# ----------------------------------------------------------------------------------------- messages
def test_sparse_config_unknown_keyword_names_the_closest_field():
    from smdm_plugin import SparseConfig

    with pytest.raises(TypeError, match="'redution'.*did you mean 'reduction'"):
        SparseConfig(redution=0.8)
    assert SparseConfig(reduction=0.5).reduction == 0.5


def test_public_namespace_is_the_public_api():
    import smdm_plugin

    names = dir(smdm_plugin)
    assert "SparseConfig" in names and "sparsify" in names
    assert not {"Any", "Dict", "List", "importlib", "TYPE_CHECKING", "annotations"} & set(names)
    assert set(names) == set(smdm_plugin.__all__)
