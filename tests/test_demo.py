"""`smdm demo --quick` on a real CMU clip (assimp-testmodels or ../shared/data/cmu-mocap)."""
import json

import numpy as np
import pytest

from smdm_plugin.apps import demo


@pytest.fixture(scope="module")
def bvh_files():
    files = demo.find_bvh()
    if not files:
        pytest.skip("no BVH clip available (apt-get install assimp-testmodels)")
    return files


def test_quick_demo_writes_tables_and_figures(bvh_files, tmp_path, capsys):
    out = tmp_path / "demo"
    rc = demo.main(["--quick", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "| vw |" in text and "sparse / dense training speed" in text and str(out) in text
    for f in ("keyframes.md", "keyframes.csv", "keyframes.png", "training.md", "loss.png", "summary.json"):
        assert (out / f).stat().st_size > 0, f
    s = json.loads((out / "summary.json").read_text())
    assert s["training"]["dense"]["steps"] == 3 and s["training"]["sparse"]["steps"] == 3
    err = s["keyframes"]["mpjpe_mm"]
    assert 0 < err["vw"]["0.8"] < 200 and err["random"]["0.8"] > 0


def test_reconstruction_error_and_features():
    T = 30
    j = np.cumsum(np.random.default_rng(0).normal(size=(T, 22, 3)), 0) * 0.01
    mask = np.zeros(T, bool)
    mask[[0, 10, 29]] = True
    err, rec = demo.reconstruction_error(j, mask)
    assert rec.shape == j.shape and err > 0
    assert demo.reconstruction_error(j, np.ones(T, bool))[0] == 0
    f = demo.motion_features(j)
    assert f.shape == (T, 66) and np.allclose(f[:, 63], j[:, 0, 1])


def test_no_bvh_message(tmp_path, capsys):
    rc = demo.main(["--bvh", str(tmp_path), "--out", str(tmp_path / "o")])
    assert rc == 2 and "assimp-testmodels" in capsys.readouterr().err
