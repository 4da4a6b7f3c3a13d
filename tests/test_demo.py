"""``smdm demo`` as a user runs it (subprocess): the quick run on real CMU clips with unusable BVH
files beside them, the trained models it leaves, and bad options / an existing output folder as
one-line errors with nothing touched."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import warnings

import numpy as np
import torch
import pytest

from smdm_plugin.apps import demo
from smdm_plugin.apps.common import keyframe_study as ks

OTHER_SKELETON = """HIERARCHY
ROOT Pelvis
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 10 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0333333
0 90 0 0 0 0 0 0 0
0 91 0 0 0 0 0 0 0
"""


def run(*args, cwd=None, timeout=900, env=None):
    return subprocess.run([sys.executable, "-m", "smdm_plugin", "demo", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout, env=env)


@pytest.fixture(scope="module")
def bvh_files(mocap_files):
    return mocap_files


def test_quick_demo_skips_unusable_files_keeps_given_flags_and_leaves_models(bvh_files, tmp_path):
    folder = tmp_path / "bvh"
    folder.mkdir()
    good = folder / "c_good.bvh"
    shutil.copy(bvh_files[0], good)
    text = good.read_text()
    (folder / "a_truncated.bvh").write_text(text[: int(len(text) * 0.7)])
    (folder / "b_other_skeleton.bvh").write_text(OTHER_SKELETON)
    out = tmp_path / "demo"
    p = run("--quick", "--batch", "3", "--bvh", str(folder), "--out", str(out), "--every", "20")
    assert p.returncode == 0, p.stderr[-3000:]
    text = p.stdout
    assert "| vw |" in text and "sparse / dense training speed" in text and str(out) in text
    assert f"smdm demo: motion from --bvh {folder}: 3 BVH file(s)" in text
    # which files were skipped and why (the reader's whole message)
    assert f"skipping {folder / 'a_truncated.bvh'}: read_bvh: {folder / 'a_truncated.bvh'}" in text and f"skipping {folder / 'b_other_skeleton.bvh'}: " in text
    assert "not a CMU skeleton" in text and "skipped 2 of 3 file(s)" in text
    # --quick applied its settings except the one given
    assert "--batch" not in text.split("smdm demo --quick:")[1].splitlines()[0]
    for f in ("keyframes.md", "keyframes.csv", "keyframes.png", "training.md", "loss.png", "summary.json",
              "inbetween.md", "inbetween.gif"):
        assert (out / f).stat().st_size > 0, f
    s = json.loads((out / "summary.json").read_text())
    assert s["options"]["batch"] == 3 and s["training"]["batch"] == 3 and s["options"]["latent"] == 32
    assert s["training"]["dense"]["steps"] == 3 and s["training"]["sparse"]["steps"] == 3
    assert [f for f, _ in s["skipped"]] == [str(folder / "a_truncated.bvh"), str(folder / "b_other_skeleton.bvh")]
    err = s["keyframes"]["mpjpe_mm"]
    assert 0 < err["vw"]["0.8"] < 200 and err["random"]["0.8"] > 0
    # j/s beside the speed it is relative to, jitter and foot skating of each model's samples and of
    # the real motion: columns, finite, consistent; --quick stops both at 3 steps: one row each
    lines = (out / "training.md").read_text().splitlines()
    assert lines[0].startswith("| model |") and lines[0].rstrip().endswith(
        "| j/s (1/s²) | jitter (m/s³) | speed (m/s) | foot skating | fid | diversity |")
    rows = {ln.split("|")[1].strip(): ln.split("|")[-7:-1] for ln in lines[2:] if ln.startswith("| ")}
    assert set(rows) == {"dense, equal steps and time", "sparse, equal steps and time", "motion capture (training clips)"}
    for name, cells in rows.items():
        if name != "motion capture (training clips)":  # (one real window in --quick: no FID for it)
            fid, div = float(cells[-2]), float(cells[-1])
            assert np.isfinite(fid) and fid >= 0 and np.isfinite(div) and div > 0, (name, cells)
        jps, jit, speed, skate = (float(v) for v in cells[:4])
        assert np.isfinite(jit) and jit >= 0 and speed > 0 and 0 <= skate <= 1, (name, cells)
        assert jps == pytest.approx(jit / speed, rel=0.02, abs=1), (name, cells)
    q = s["training"]["quality"]
    assert q["motion capture"]["jitter"] > 0 and all(np.isfinite(q[m]["jps"]) for m in ("dense", "sparse"))
    assert s["training"]["equal_steps"]["steps"] == 3 and "32 unconditional samples per model" in text
    # the in-betweening table: keyframes exact for both models
    rows = [r for r in (out / "inbetween.md").read_text().splitlines() if r.startswith("| dense") or r.startswith("| sparse")]
    assert len(rows) == 2 and all(r.split("|")[3].strip() == "0.0" for r in rows)
    from PIL import Image

    assert Image.open(out / "inbetween.gif").n_frames == 60  # 120 frames, every 2nd in --quick
    # the trained models are folders smdm inbetween reads
    from smdm_plugin.training.bundle import load_bundle

    assert load_bundle(str(out / "sparse")).sparse and not load_bundle(str(out / "dense")).sparse
    # a second run into the same folder is refused, nothing changes; --overwrite is accepted
    before = {f.name: f.stat().st_mtime_ns for f in out.iterdir()}
    p = run("--quick", "--bvh", str(good), "--out", str(out))
    assert p.returncode == 2 and "--overwrite" in p.stderr and "Traceback" not in p.stderr
    assert {f.name: f.stat().st_mtime_ns for f in out.iterdir()} == before


@pytest.mark.parametrize("args, message", [
    (["--minutes", "-1"], "argument --minutes: must be a finite number in (0, 1440], got -1"),
    (["--minutes", "0"], "argument --minutes"),
    (["--batch", "0"], "argument --batch: must be an integer in [1, 4096], got 0"),
    (["--frames", "500"], "argument --frames"),
    (["--reductions", "0.5", "1.0"], "argument --reductions"),
    (["--train-reduction", "nan"], "argument --train-reduction"),
    (["--latent", "30"], "argument --latent: must be a multiple of 4"),
    (["--threads", "0"], "argument --threads"),
    (["--seed", "-3"], "argument --seed"),
    (["--device", "cuda:3"], "argument --device"),
    (["--device", "tpu"], "argument --device"),
])
def test_bad_options_are_one_line_errors(args, message, tmp_path, capsys):
    out = tmp_path / "never"
    with pytest.raises(SystemExit) as e:
        demo.main([*args, "--out", str(out)])
    err = capsys.readouterr().err
    assert e.value.code == 2
    last = err.strip().splitlines()[-1]
    assert last.startswith("smdm demo: error: ") and message in last, err
    assert not out.exists()


def test_quick_demo_runs_on_the_embedded_clips(tmp_path):
    """No --bvh, no $SMDM_MOCAP, no ../shared: the clips shipped in the package."""
    env = {k: v for k, v in os.environ.items() if k != "SMDM_MOCAP"}
    p = run("--quick", "--no-gif", "--out", str(tmp_path / "o"), cwd=tmp_path, env=env)
    assert p.returncode == 0, p.stderr[-3000:]
    assert "smdm demo: motion from the 17 CMU clips embedded in the package" in p.stdout
    assert (tmp_path / "o" / "training.md").exists() and "| motion capture (" in p.stdout
    # FID and diversity of each model's samples against the real crops, from the evaluator the demo
    # trained on its clips and left in OUT/evaluator (a joints66 evaluator smdm eval / the demo reuse)
    q = json.loads((tmp_path / "o" / "summary.json").read_text())["training"]["quality"]
    for m in ("dense", "sparse"):
        assert np.isfinite(q[m]["fid"]) and q[m]["fid"] >= 0 and np.isfinite(q[m]["diversity"]) and q[m]["diversity"] > 0
    assert "R-precision and matching score are not reported" in p.stdout
    from smdm_plugin.metrics.evaluator.model import load_evaluator

    ev = load_evaluator(str(tmp_path / "o" / "evaluator"))
    assert (ev.config.representation, ev.config.dim_pose) == ("joints66", 66)
    # reused with --evaluator: same FID for the same seed; --no-evaluator: no FID
    p = run("--quick", "--no-gif", "--evaluator", str(tmp_path / "o" / "evaluator"), "--out", str(tmp_path / "r"),
            cwd=tmp_path, env=env)
    assert p.returncode == 0, p.stderr[-3000:]
    assert not (tmp_path / "r" / "evaluator").exists() and "## Evaluator" not in p.stdout
    q2 = json.loads((tmp_path / "r" / "summary.json").read_text())["training"]["quality"]
    assert q2["dense"]["fid"] == pytest.approx(q["dense"]["fid"], rel=1e-4, abs=1e-4)
    p = run("--quick", "--no-gif", "--no-evaluator", "--out", str(tmp_path / "n"), cwd=tmp_path, env=env)
    assert p.returncode == 0 and "fid" not in json.loads((tmp_path / "n" / "summary.json").read_text())["training"][
        "quality"]["dense"] and not (tmp_path / "n" / "evaluator").exists()


def test_bad_options_as_a_user_runs_them(tmp_path):
    for args, message in ((["--minutes", "-1"], "argument --minutes: must be a finite number in (0, 1440], got -1"),
                          (["--device", "cuda:3"], "argument --device")):
        p = run(*args, "--out", str(tmp_path / "never"))
        assert p.returncode == 2 and "Traceback" not in p.stderr
        assert p.stderr.strip().splitlines()[-1].startswith("smdm demo: error: ") and message in p.stderr
    assert not (tmp_path / "never").exists()


def test_existing_output_folder_is_refused(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    p = run("--quick", "--out", str(out))
    assert p.returncode == 2 and "exists and is not empty; pass --overwrite" in p.stderr
    assert [f.name for f in out.iterdir()] == ["notes.txt"] and (out / "notes.txt").read_text() == "keep me"
    (tmp_path / "file").write_text("x")
    p = run("--out", str(tmp_path / "file"))
    assert p.returncode == 2 and "is not a folder" in p.stderr


def test_quick_keeps_given_flags():
    p = __import__("argparse").ArgumentParser()
    demo.add_arguments(p)
    a = p.parse_args(["--quick", "--frames", "100", "--reductions", "0.5"])
    applied = demo.apply_quick(a)
    assert (a.frames, a.reductions, a.batch, a.latent, a.layers, a.max_clips) == (100, [0.5], 4, 32, 1, 1)
    assert not any(s.startswith(("--frames", "--reductions")) for s in applied)
    a = p.parse_args(["--batch", "8"])
    assert demo.apply_quick(a) == [] and (a.frames, a.batch, a.latent) == (120, 8, 256)


def test_load_clips_reports_warnings_and_skips(monkeypatch):
    import smdm_plugin.io.bvh as bvh

    def fake(path, fps=20):
        if "odd" in path:
            warnings.warn(f"{path}: one extra motion row ignored", UserWarning)
        if "bad" in path:
            raise ValueError(f"read_bvh: {path}: Frame Time must be > 0")
        return np.zeros((40 if "short" not in path else 5, 22, 3))

    monkeypatch.setattr(bvh, "load_cmu_clip", fake)
    log, skipped = [], []
    clips = ks.load_clips(["odd.bvh", "bad.bvh", "short.bvh", "ok.bvh"], log=log.append, skipped=skipped)
    assert [n for n, _ in clips] == ["odd", "ok"]
    assert log[0] == "  note: odd.bvh: one extra motion row ignored (UserWarning)"
    assert skipped == [("bad.bvh", "read_bvh: bad.bvh: Frame Time must be > 0"),
                       ("short.bvh", "only 5 frames at 20 fps (20 needed)")]


def test_reconstruction_error_and_features():
    T = 30
    j = np.cumsum(np.random.default_rng(0).normal(size=(T, 22, 3)), 0) * 0.01
    mask = np.zeros(T, bool)
    mask[[0, 10, 29]] = True
    err, rec = ks.reconstruction_error(j, mask)
    assert rec.shape == j.shape and err > 0
    assert ks.reconstruction_error(j, np.ones(T, bool))[0] == 0
    f = demo.motion_features(j)
    assert f.shape == (T, 66) and np.allclose(f[:, 63], j[:, 0, 1])
    assert np.allclose(f[0, 64:], 0) and np.allclose(f[:, 64:] + j[0, 0, [0, 2]], j[:, 0, [0, 2]], atol=1e-6)


def test_no_bvh_message(tmp_path, capsys, monkeypatch):
    (tmp_path / "in").mkdir()  # an --out inside --bvh would be refused as overlapping the input
    rc = demo.main(["--bvh", str(tmp_path / "in"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and f"no .bvh file in --bvh {tmp_path / 'in'}" in err and "SMDM_MOCAP" in err
    monkeypatch.setenv("SMDM_MOCAP", str(tmp_path / "absent"))
    assert demo.main(["--out", str(tmp_path / "o")]) == 2
    assert "SMDM_MOCAP=" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_motion_source_order(tmp_path, monkeypatch, request):
    """--bvh, else $SMDM_MOCAP, else the embedded clips."""
    from smdm_plugin.io.embedded import embedded_clips

    monkeypatch.delenv("SMDM_MOCAP", raising=False)
    source, files, clips = ks.motion_source(None, max_clips=2)
    assert "embedded" in source and files == [] and [n for n, _ in clips] == [n for n, _ in embedded_clips()[:2]]
    mocap = request.getfixturevalue("mocap_files")  # skips here when the shared clips are absent
    monkeypatch.setenv("SMDM_MOCAP", os.path.dirname(mocap[0]))
    source, files, clips = ks.motion_source(None, max_clips=1)
    assert "$SMDM_MOCAP" in source and files == mocap and len(clips) == 1
    one = tmp_path / "one"
    one.mkdir()
    shutil.copy(files[0], one / "x.bvh")
    source, files, clips = ks.motion_source([str(one)])
    assert source == f"--bvh {one}" and files == [str(one / "x.bvh")] and [n for n, _ in clips] == ["x"]


def test_bvh_warning_is_shown(tmp_path, mocap_files):
    """A tolerated oddity of a real file (one motion row too many) is shown with its category."""
    from pathlib import Path

    lines = Path(mocap_files[0]).read_text().rstrip("\n").splitlines()
    f = tmp_path / "extra.bvh"
    f.write_text("\n".join(lines + [lines[-1]]) + "\n")
    log = []
    clips = ks.load_clips([str(f)], log=log.append)
    assert len(clips) == 1 and len(log) == 1
    assert log[0].startswith(f"  note: read_bvh: {f}") and log[0].endswith("(BVHWarning)")


class _FakeDist:
    distributed, is_main, device = False, True, "cpu"


class _FakeTrainer:
    """Steps that take ``cost`` seconds (slept), a 'model' whose weight counts the steps."""

    def __init__(self, cost):
        import torch

        self.cost, self.dist, self.model = cost, _FakeDist(), torch.nn.Linear(1, 1, bias=False)
        self.model.weight.data.zero_()

    def step(self):
        import time

        time.sleep(self.cost)
        self.model.weight.data += 1
        return float(self.model.weight)


def test_race_fair_gives_equal_steps_then_equal_time():
    from smdm_plugin.training.trainer import race_fair

    slow, fast = _FakeTrainer(0.02), _FakeTrainer(0.005)
    r = race_fair({"dense": slow, "sparse": fast}, seconds=0.6)
    eq = r["equal_steps"]
    S = eq["steps"]
    assert r["dense"]["steps"] == S and r["sparse"]["steps"] > 2 * S            # fast trains on
    assert float(eq["states"]["sparse"]["weight"]) == S                        # its weights at S steps
    assert float(fast.model.weight) == r["sparse"]["steps"] and "dense" not in eq["states"]
    assert r["sparse"]["seconds"] == pytest.approx(r["dense"]["seconds"], rel=0.2)   # equal time
    assert r["dense"]["seconds"] >= 0.3 and eq["seconds"]["sparse"] < 0.5 * eq["seconds"]["dense"]
    assert r["speed_ratio"] > 2
    capped = race_fair({"dense": _FakeTrainer(0.0), "sparse": _FakeTrainer(0.0)}, max_steps=4)
    assert capped["equal_steps"]["steps"] == 4 and capped["equal_steps"]["states"] == {}
    assert capped["dense"]["steps"] == capped["sparse"]["steps"] == 4
    with pytest.raises(ValueError, match="race_fair: need seconds > 0"):
        race_fair({"dense": slow}, seconds=0)


def _random_joints66_evaluator():
    """An untrained joints66 evaluator (random weights: FID is a distance in any fixed embedding)."""
    from smdm_plugin.io.embedded import embedded_clips
    from smdm_plugin.metrics.evaluator.data import clips_captioned
    from smdm_plugin.metrics.evaluator.train import TrainSettings, build_evaluator

    train = clips_captioned(embedded_clips()[:3], {}, (0.0, 1.0))
    return build_evaluator(train, TrainSettings(seed=0)).eval()


def test_evaluator_scores_real_against_itself_is_zero_and_noise_is_not():
    """The demo's FID hook: real crops scored against themselves give FID 0 (same embeddings),
    a noised copy a clearly positive FID; the hook embeds the real joints as joints66 features."""
    from smdm_plugin.io.embedded import embedded_clips
    from smdm_plugin.metrics import frechet_distance
    from smdm_plugin.metrics.evaluator.score import embed_motions

    ev = _random_joints66_evaluator()
    clips = embedded_clips()
    ref = np.stack(demo.training_crops([c for c in clips if len(c[1]) >= 120], 120, stride=30))   # [W, 120, 22, 3]
    real = demo.real_set(ref)
    assert real.features.shape == (len(ref), 120, 66) and real.representation == "joints66"
    assert np.allclose(real.features[3].numpy(), demo.motion_features(ref[3]))
    rng = np.random.default_rng(0)
    noisy = demo.real_set(ref + rng.normal(0, 0.05, ref.shape).astype(np.float32))
    s = demo.evaluator_scores({"real": real, "noisy": noisy}, ref, ev)
    assert s["real"]["fid"] == pytest.approx(0.0, abs=1e-6) and s["noisy"]["fid"] > 1e-3
    # the same number as FID of the embeddings computed directly
    direct = frechet_distance(embed_motions(ev, [demo.motion_features(w) for w in ref]),
                              embed_motions(ev, noisy.features.numpy()))
    assert s["noisy"]["fid"] == pytest.approx(direct, rel=1e-9)
    assert s["real"]["diversity"] > 0 and demo.evaluator_scores({"real": real}, ref, None) == {}


def test_mismatched_evaluator_is_one_line(tmp_path, capsys):
    """An evaluator for another representation (HumanML3D's 263-D) or a folder that is none: one
    line, exit 2, nothing written; the hook refuses a set in another representation."""
    import torch

    from smdm_plugin.metrics.evaluator.model import Evaluator, EvaluatorConfig, save_evaluator

    cfg = EvaluatorConfig(dim_pose=263, dim_word=8, dim_movement_hidden=8, dim_movement_latent=8, dim_motion_hidden=8,
                          dim_text_hidden=8, dim_coemb=8, vocab_size=4, learned_words=True, source="own")
    ev = Evaluator(cfg, {"unk": 0, "a": 1, "sos/OTHER": 2, "eos/OTHER": 3}, np.zeros(263), np.ones(263))
    save_evaluator(ev, str(tmp_path / "hml"))
    for path, message in ((tmp_path / "hml", "reads humanml3d features of width 263; the demo's models generate "
                                             "joints66 of width 66"), (tmp_path / "none", "argument --evaluator: ")):
        out = tmp_path / "never"
        with pytest.raises(SystemExit) as e:
            demo.main(["--evaluator", str(path), "--out", str(out)])
        err = capsys.readouterr().err.strip().splitlines()
        assert e.value.code == 2 and err[-1].startswith("smdm demo: error: argument --evaluator: ")
        assert message in err[-1] and not out.exists()
    with pytest.raises(SystemExit):
        demo.main(["--evaluator", str(tmp_path / "hml"), "--no-evaluator", "--out", str(tmp_path / "never")])
    assert "not allowed with argument --evaluator" in capsys.readouterr().err
    g = demo.GeneratedSet(torch.zeros(2, 60, 66), torch.full((2,), 60), torch.zeros(2, 60, 22, 3), "joints66")
    with pytest.raises(ValueError, match="evaluator reads humanml3d"):
        demo.evaluator_scores({"dense": g}, np.zeros((2, 60, 22, 3), np.float32), ev)


def test_loss_plot_legend_and_title_give_the_same_speed():
    """0.4.0's title said "sparse runs 4.09x the steps per second" while its legend read 0.68 vs
    1.67 steps/s (whole-run rates): the legend now shows the equal-steps rates the title compares."""
    from smdm_plugin.apps.demo import equal_step_rates
    from smdm_plugin.training.trainer import race_fair

    train = race_fair({"dense": _FakeTrainer(0.004), "sparse": _FakeTrainer(0.001)}, seconds=0.2, progress=False)
    rates = equal_step_rates(train)
    assert rates["sparse"] / rates["dense"] == pytest.approx(train["speed_ratio"], rel=1e-9)
