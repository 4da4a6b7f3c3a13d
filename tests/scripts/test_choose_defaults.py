"""The measurement scripts behind docs/defaults.md run end to end on the real clips (tiny
settings), resume, and refuse to mix grids in one results folder."""
import importlib.util
import json
from pathlib import Path

import pytest

from helpers.paths import ROOT


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_choose_training_defaults_runs_and_resumes(hml_dir, tmp_path, capsys):
    script = _script("choose_training_defaults")
    out = tmp_path / "res"
    argv = ["--grid", "quick", "--only", "dense", "sparse (VW)", "--seeds", "0", "--steps", "2", "--samples", "2",
            "--data", str(hml_dir), "--out", str(out)]
    assert script.main(argv) == 0
    run = json.loads((out / "sparse-vw" / "seed0.json").read_text())
    assert run["steps"] == 2 and run["sparse_config"]["reduction"] == 0.8
    for key in ("val_loss", "kf_interp_mm", "jitter", "foot_skating", "ees"):
        assert run[key] >= 0.0
    dense = json.loads((out / "dense" / "seed0.json").read_text())
    assert dense["kf_interp_mm"] is None and dense["sparse_config"] is None
    text = (out / "results.md").read_text()
    assert "| sparse (VW) |" in text and "| real held-out motions |" in text
    # a second call reuses the runs (no training): the files are unchanged
    before = (out / "sparse-vw" / "seed0.json").stat().st_mtime_ns
    assert script.main(argv) == 0
    assert (out / "sparse-vw" / "seed0.json").stat().st_mtime_ns == before
    # another grid into the same folder is refused without --overwrite (argparse: exit 2)
    with pytest.raises(SystemExit) as e:
        script.main(["--grid", "quick", "--steps", "3", "--out", str(out), "--data", str(hml_dir)])
    assert e.value.code == 2
    assert "holds runs of another grid" in capsys.readouterr().err


def test_choose_training_defaults_cell_format():
    script = _script("choose_training_defaults")
    assert script._cell([1.0, 3.0], ".1f") == "2.0 ± 1.4"
    assert script._cell([None, 2.0], ".2f") == "2.00"
    assert script._cell([None], ".2f") == "—"


@pytest.mark.parametrize("grid", ["frame_index_scale", "frame_index_scale_dynamic", "training_defaults"])
def test_defaults_grids_are_valid_ablation_grids(grid):
    """The grids behind docs/defaults.md load as `smdm ablate` grids on the paper's recipe, every
    variant is a valid SparseConfig, and no two variants run the same configuration."""
    from smdm_plugin.apps.ablate import grid as grids

    cfg = grids.load_config(grid)
    base = grids.sparse_config(cfg, {"name": "base"})
    assert base.fsq and base.lipschitz_lambda == 0.0 and cfg["model"]["arch"] == "trans_dec"
    assert base.dynamic_update is (cfg["diffusion_steps"] >= 100)     # Table 2's rule
    configs = [grids.sparse_config(cfg, v).to_dict() for v in cfg["variants"]]
    assert all(configs.count(c) == 1 for c in configs)


def test_measure_smooth_sampling_runs_on_the_embedded_clips(tmp_path, capsys):
    """The script behind docs/defaults.md's smooth-sampling table, at toy size: one row per model and
    variant and the real motion, j/s = jitter / speed; an existing --out needs --overwrite."""
    script = _script("measure_smooth_sampling")
    out = tmp_path / "smooth.md"
    argv = ["--seeds", "1", "--steps", "1", "--samples", "2", "--frames", "40", "--latent", "16", "--layers", "1",
            "--batch", "2", "--diffusion-steps", "4", "--variants", "cubic, dynamic off", "--out", str(out)]
    assert script.main(argv) == 0
    rows = [r for r in out.read_text().splitlines() if r.startswith("| ") and "---" not in r][1:]
    assert [r.split("|")[1].strip() for r in rows][:2] == ["dense", "sparse: cubic, dynamic off"]
    assert rows[2].startswith("| real motion (")
    saved = json.loads(out.with_suffix(".json").read_text())
    for r in saved["rows"]["dense"] + [saved["real"]]:
        assert r["jps"] == pytest.approx(r["jitter"] / r["speed"]) and 0 <= r["skating"] <= 1
    with pytest.raises(SystemExit):
        script.main(argv)
    assert "--overwrite" in capsys.readouterr().err
