"""`smdm ablate` on the quick grid (real motion from ../shared/data/cmu-humanml3d)."""
import json
import os
from pathlib import Path

import pytest

from smdm_plugin.apps import ablate

ROOT = Path(__file__).resolve().parents[1]
QUICK = ROOT / "smdm_plugin" / "configs" / "ablations" / "quick.yaml"


def test_table1_config_lists_the_paper_ablations():
    cfg = ablate.load_config(str(ROOT / "smdm_plugin" / "configs" / "ablations" / "table1.yaml"))
    names = [v["name"] for v in cfg["variants"]]
    assert names[0] == "dense" and len(names) == 9
    for v in cfg["variants"]:
        ablate.sparse_config(cfg, v)  # every variant is a valid SparseConfig
    sels = {ablate.sparse_config(cfg, v).selector for v in cfg["variants"] if not v.get("dense")}
    assert sels == {"vw", "random", "uniform", "mdo"}


def test_bad_config_is_a_clear_error():
    with pytest.raises(ValueError, match="unique name"):
        ablate.resolve({"variants": [{"name": "a"}, {"name": "a"}]})
    with pytest.raises(ValueError, match="no variants"):
        ablate.resolve({})


def test_quick_grid_runs_resumes_and_records_failures(hml_dir, tmp_path, monkeypatch):
    out = tmp_path / "abl"
    rc = ablate.main(["--config", str(QUICK), "--out", str(out), "--data", str(hml_dir), "--no-progress"])
    assert rc == 0
    md = (out / "results.md").read_text()
    for name in ("dense", "sparse (VW)", "w/o interpolation", "FSQ keys"):
        assert f"| {name} | ok |" in md
    assert (out / "results.csv").exists() and (out / "loss_curves.png").stat().st_size > 0
    assert (out / "config.yaml").exists() and (out / "dense" / "config.json").exists()
    res = json.loads((out / "sparse-vw" / "result.json").read_text())
    dense = json.loads((out / "dense" / "result.json").read_text())
    assert res["keyframe_error_mm"] > 0 and dense["keyframe_error_mm"] is None
    assert len(res["losses"]) == 3 and res["ees"] is not None
    assert 0 < res["val_loss"] < 100 and 0 < dense["val_loss"] < 100  # same fixed noise and timesteps

    # resumable: finished variants are skipped; a crashing one is recorded, the others survive
    calls = []
    real = ablate.run_variant

    def flaky(cfg, variant, *a, **k):
        calls.append(variant["name"])
        if variant["name"] == "FSQ keys":
            raise RuntimeError("boom")
        return real(cfg, variant, *a, **k)

    os.remove(out / "fsq-keys" / "result.json")
    monkeypatch.setattr(ablate, "run_variant", flaky)
    rc = ablate.main(["--config", str(QUICK), "--out", str(out), "--data", str(hml_dir), "--no-progress"])
    assert rc == 1 and calls == ["FSQ keys"]
    assert "boom" in json.loads((out / "fsq-keys" / "failed.json").read_text())["error"]
    md = (out / "results.md").read_text()
    assert "| FSQ keys | failed |" in md and "| dense | ok |" in md


def test_missing_data_is_a_clear_message(tmp_path, capsys):
    rc = ablate.main(["--config", str(QUICK), "--out", str(tmp_path / "x"), "--data", str(tmp_path / "none")])
    assert rc == 2 and "no HumanML3D-format data" in capsys.readouterr().err
