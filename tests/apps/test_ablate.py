"""`smdm ablate`: the quick grid on real motion (../shared/data/cmu-humanml3d), and the results
folder's provenance, caching, --resume / --overwrite / --only semantics, failures and interrupts
(on a small synthetic HumanML3D-format folder, with the training replaced by a recorder)."""
import json
import os
from pathlib import Path

import numpy as np
import pytest

import smdm_plugin
from smdm_plugin.apps import ablate
from smdm_plugin.apps.ablate import grid as grids
from smdm_plugin.apps.ablate import report

from helpers.grids import GRID
from helpers.paths import ROOT
from helpers.synthetic_data import write_humanml3d

QUICK = ROOT / "configs" / "ablations" / "quick.yaml"


def test_table1_config_lists_the_paper_ablations():
    cfg = grids.load_config(str(ROOT / "configs" / "ablations" / "table1.yaml"))
    names = [v["name"] for v in cfg["variants"]]
    assert names[0] == "dense" and len(names) == 9
    for v in cfg["variants"]:
        grids.sparse_config(cfg, v)  # every variant is a valid SparseConfig
    sels = {grids.sparse_config(cfg, v).selector for v in cfg["variants"] if not v.get("dense")}
    assert sels == {"vw", "random", "uniform", "mdo"}
    from smdm_plugin.apps.ablate import study

    for name in grids.packaged_grids():  # every packaged grid resolves (a study config as a study)
        (study.load_study if study.is_study_config(name) else grids.load_config)(name)


@pytest.mark.parametrize("cfg,match", [
    ({"variants": [{"name": "a"}, {"name": "a"}]}, r"variants 'a' and 'a' have the same name"),
    ({"variants": [{"name": "sparse (VW)"}, {"name": "Sparse VW"}]},
     r"variants 'sparse \(VW\)' and 'Sparse VW' have the same folder name 'sparse-vw'"),
    ({}, "no variants"),
    ({"stpes": 5, "variants": [{"name": "a"}]}, r"unknown key 'stpes'; did you mean 'steps'\?"),
    ({"steps": 0, "variants": [{"name": "a"}]}, r"steps=0: expected an integer >= 1"),
    ({"steps": "5", "variants": [{"name": "a"}]}, r"steps='5': expected an integer >= 1"),
    ({"steps": 2.5, "variants": [{"name": "a"}]}, r"steps=2.5: expected an integer"),
    ({"lr": -1e-3, "variants": [{"name": "a"}]}, r"lr=-0.001: expected a finite number > 0"),
    ({"model": {"latnet_dim": 8}, "variants": [{"name": "a"}]}, r"model: unknown key 'latnet_dim'; did you mean 'latent_dim'"),
    ({"eval": {"frames": 1}, "variants": [{"name": "a"}]}, r"eval.frames=1: expected an integer >= 2"),
    ({"variants": [{"name": "a", "dense": "yes"}]}, r"variants\[0\].dense='yes': expected true or false"),
    ({"variants": [{"name": "a", "spares": {}}]}, r"variants\[0\]: unknown key 'spares'; did you mean 'sparse'"),
    ({"variants": [{"dense": True}]}, r"variants\[0\]: every variant needs a unique name"),
    ({"variants": ["dense"]}, r"variants\[0\]='dense': expected a mapping"),
    # sparse settings on a dense variant cannot apply (0.10.5 trained it dense and dropped them)
    ({"variants": [{"name": "d", "dense": True, "sparse": {"reduction": 0.5}}]},
     r"variants\[0\] \('d'\): sparse settings \['reduction'\] do not apply to a dense variant"),
])
def test_bad_grid_is_a_clear_error(cfg, match):
    with pytest.raises(ValueError, match=match):
        grids.resolve(cfg)


def test_bad_grid_file_errors_name_the_file(tmp_path):
    p = tmp_path / "g.yaml"
    p.write_text("steps: [1\n")
    with pytest.raises(ValueError, match=rf"{p}: not valid YAML"):
        grids.load_config(str(p))
    p.write_text("steps: 0\nvariants: [{name: a}]\n")
    with pytest.raises(ValueError, match=rf"{p}: steps=0"):
        grids.load_config(str(p))
    with pytest.raises(FileNotFoundError, match=r"--config 'tabel1' is neither a file nor a packaged grid .*did you "
                                                r"mean 'table1'"):
        grids.load_config("tabel1")


# ------------------------------------------------------------------------------ the results folder
@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return write_humanml3d(tmp_path_factory.mktemp("hml"))


class Recorder:
    """Stands in for ``run_variant`` (the training loop): records which variants run, fails the
    ones named in ``fail`` (or raises ``interrupt_at`` as Ctrl-C), and validates the variant's
    sparse config as the real one does."""

    def __init__(self):
        self.calls, self.fail, self.interrupt_at, self.total = [], set(), None, 0

    def __call__(self, cfg, variant, data, device, progress=False, dist=None, checkpoint_dir=None):
        name = variant["name"]
        if name == self.interrupt_at:
            raise KeyboardInterrupt
        self.calls.append(name)
        self.total += 1
        sc = grids.sparse_config(cfg, variant)
        if name in self.fail:
            raise RuntimeError(f"boom in {name}")
        steps = int(cfg["steps"])
        return {"name": name, "status": "ok", "steps": steps, "final_loss": 1.0 + 0.01 * self.total,
                "best_loss": 0.9, "val_loss": 1.5, "steps_per_s": 10.0, "train_s": 0.1, "sample_s": 0.1,
                "keyframe_error_mm": None if sc is None else 12.5, "ees": 3.0, "losses": [1.0] * steps,
                "sparse_config": None if sc is None else sc.to_dict()}


@pytest.fixture
def rec(monkeypatch):
    r = Recorder()
    monkeypatch.setattr(ablate, "run_variant", r)
    return r


def grid(tmp_path, text=GRID):
    p = tmp_path / "grid.yaml"
    p.write_text(text)
    return p


def run(tmp_path, data_dir, *extra, config=None):
    return ablate.main(["--config", str(config or grid(tmp_path)), "--out", str(tmp_path / "out"),
                        "--data", str(data_dir), "--no-progress", *extra])


def snapshot(folder):
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(Path(folder).rglob("*")) if p.is_file()}


def table_rows(out, reference=False):
    """``{variant: [status, final loss, ..., wall]}`` from results.md's table (with ``reference``,
    the real validation motion's row too)."""
    md = (out / "results.md").read_text()
    cells = [[c.strip() for c in ln.strip().strip("|").split("|")] for ln in md.splitlines() if ln.startswith("| ")]
    skip = ("variant", "---") + (() if reference else (report.REFERENCE_ROW,))
    return {c[0]: c[1:] for c in cells if c[0] not in skip}


def test_results_record_provenance(tmp_path, data_dir, rec):
    assert run(tmp_path, data_dir) == 0
    out = tmp_path / "out"
    res = json.loads((out / "uniform" / "result.json").read_text())
    prov = res["provenance"]
    assert prov["package_version"] == smdm_plugin.__version__ and prov["steps"] == 2 and prov["seed"] == 0
    assert prov["device"] == "cpu" and len(prov["config_hash"]) == 16 and len(prov["data_fingerprint"]) == 16
    assert prov["settings"]["sparse_config"]["selector"] == "uniform" and prov["settings"]["model"]["latent_dim"] == 16
    cfgj = json.loads((out / "uniform" / "config.json").read_text())
    assert cfgj == prov["settings"]
    # the data fingerprint covers every file read: the listings, Mean/Std and each motion + joints
    assert prov["data_files"] == 2 + 2 + 2 * 6
    manifest = json.loads((out / "ablate.json").read_text())
    assert manifest["tool"] == "smdm ablate" and manifest["variants"] == ["dense", "sparse (VW)", "uniform"]
    assert not list(out.rglob("*.tmp")) and not list(out.rglob(".*"))  # atomic writes leave nothing behind


def test_rerun_without_flags_refuses_and_touches_nothing(tmp_path, data_dir, rec, capsys):
    assert run(tmp_path, data_dir) == 0 and len(rec.calls) == 3
    before = snapshot(tmp_path / "out")
    capsys.readouterr()
    assert run(tmp_path, data_dir) == 2
    err = capsys.readouterr().err
    assert "already holds ablation results" in err and "--resume" in err and "--overwrite" in err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert snapshot(tmp_path / "out") == before and len(rec.calls) == 3


def test_resume_reuses_only_results_with_the_same_provenance(tmp_path, data_dir, rec, capsys):
    assert run(tmp_path, data_dir) == 0
    before = snapshot(tmp_path / "out")
    assert run(tmp_path, data_dir, "--resume") == 0 and len(rec.calls) == 3  # nothing ran again
    assert "Reused from an earlier run with the same provenance: dense, sparse (VW), uniform." in \
        (tmp_path / "out" / "results.md").read_text()
    for slug in ("dense", "sparse-vw", "uniform"):
        assert snapshot(tmp_path / "out")[f"{slug}/result.json"] == before[f"{slug}/result.json"]

    # other steps: refused before anything trains, naming what differs; files untouched
    before = snapshot(tmp_path / "out")
    capsys.readouterr()
    assert run(tmp_path, data_dir, "--resume", "--steps", "3") == 2
    err = capsys.readouterr().err
    assert "holds 3 result(s) from another run" in err and "steps 2 -> 3" in err and "--overwrite" in err
    assert snapshot(tmp_path / "out") == before and len(rec.calls) == 3
    # --overwrite runs them again
    assert run(tmp_path, data_dir, "--overwrite", "--steps", "3") == 0 and len(rec.calls) == 6
    assert json.loads((tmp_path / "out" / "dense" / "result.json").read_text())["provenance"]["steps"] == 3


def _edit_data(root):
    """Same file names, sizes and mtimes; one value changed: only the contents tell."""
    f = root / "new_joint_vecs" / "train001.npy"
    st = f.stat()
    a = np.load(f)
    a[3, 7] += 1.0
    np.save(f, a)
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert f.stat().st_size == st.st_size


@pytest.mark.parametrize("change,reason,stale", [
    ("data", "data changed (fingerprint", 3),
    ("version", f"package version {smdm_plugin.__version__} -> 9.9.9", 3),
    ("seed", "seed 0 -> 1", 3),
    ("variant", "settings changed: sparse_config.selector 'uniform' -> 'random'", 1),
    ("shared", "settings changed: lr 0.0002 -> 0.0003", 3),
])
def test_resume_detects_every_kind_of_change(tmp_path, rec, capsys, monkeypatch, change, reason, stale):
    data = write_humanml3d(tmp_path / "data")
    assert run(tmp_path, data, config=grid(tmp_path)) == 0
    text = GRID
    if change == "data":
        _edit_data(data)
    elif change == "version":
        monkeypatch.setattr(smdm_plugin, "__version__", "9.9.9")
    elif change == "seed":
        text = GRID.replace("seed: 0", "seed: 1")
    elif change == "variant":
        text = GRID.replace("selector: uniform", "selector: random")
    else:
        text = GRID.replace("steps: 2\n", "steps: 2\nlr: 0.0003\n")
    before = snapshot(tmp_path / "out")
    capsys.readouterr()
    assert run(tmp_path, data, "--resume", config=grid(tmp_path, text)) == 2
    err = capsys.readouterr().err
    assert f"holds {stale} result(s) from another run" in err and reason in err, err
    assert snapshot(tmp_path / "out") == before and len(rec.calls) == 3


def test_only_updates_those_rows_and_keeps_the_others(tmp_path, data_dir, rec):
    assert run(tmp_path, data_dir) == 0
    out = tmp_path / "out"
    first = table_rows(out)
    changed = grid(tmp_path, GRID.replace("selector: uniform", "selector: random"))
    rec.calls.clear()
    assert run(tmp_path, data_dir, "--only", "dense", "--overwrite", config=changed) == 0
    assert rec.calls == ["dense"]
    rows = table_rows(out)
    assert list(rows) == ["dense", "sparse (VW)", "uniform"]
    assert rows["dense"][0] == "ok" and rows["dense"][1] != first["dense"][1]     # new numbers
    assert rows["sparse (VW)"] == first["sparse (VW)"]                            # kept as it was
    assert rows["uniform"][0] == "stale" and set(rows["uniform"][1:7]) == {"—"}   # not mixed in
    md = (out / "results.md").read_text()
    assert "uniform: stale, not shown (settings changed: sparse_config.selector 'uniform' -> 'random'" in md
    assert len((out / "results.csv").read_text().splitlines()) == 5  # header, 3 variants, real motion
    # the folder name works too; then every row is current again
    assert run(tmp_path, data_dir, "--only", "uniform", "--overwrite", config=changed) == 0
    assert rec.calls == ["dense", "uniform"] and table_rows(out)["uniform"][0] == "ok"
    assert run(tmp_path, data_dir, "--resume", config=changed) == 0 and rec.calls == ["dense", "uniform"]


def test_only_in_a_new_folder_lists_the_rest_as_not_run(tmp_path, data_dir, rec):
    assert run(tmp_path, data_dir, "--only", "sparse-vw") == 0 and rec.calls == ["sparse (VW)"]
    rows = table_rows(tmp_path / "out")
    assert rows["dense"][0] == "not run" and rows["sparse (VW)"][0] == "ok"
    assert "Not run yet: dense, uniform." in (tmp_path / "out" / "results.md").read_text()


def test_only_unknown_name_is_an_argparse_error(tmp_path, data_dir, rec, capsys):
    with pytest.raises(SystemExit) as e:
        run(tmp_path, data_dir, "--only", "dense", "sparce (VW)")
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith("usage: smdm ablate")
    assert "argument --only: unknown variant(s) 'sparce (VW)'; did you mean 'sparse (VW)'?; known: 'dense', " \
           "'sparse (VW)', 'uniform'" in err
    assert not (tmp_path / "out").exists() and rec.calls == []


def test_a_failing_variant_is_recorded_and_the_others_finish(tmp_path, data_dir, rec):
    text = GRID + "  - {name: bad reduction, sparse: {reduction: 1.5}}\n"
    rec.fail = {"uniform"}
    assert run(tmp_path, data_dir, config=grid(tmp_path, text)) == 1
    out = tmp_path / "out"
    assert rec.calls == ["dense", "sparse (VW)", "uniform", "bad reduction"]
    rows = table_rows(out)
    assert [rows[n][0] for n in rows] == ["ok", "ok", "failed", "failed"]
    assert "boom in uniform" in json.loads((out / "uniform" / "failed.json").read_text())["error"]
    bad = json.loads((out / "bad-reduction" / "failed.json").read_text())
    assert "SparseConfig.reduction=1.5" in bad["error"] and not (out / "bad-reduction" / "result.json").exists()
    # --resume runs the failed ones again (and only them)
    rec.fail, rec.calls = set(), []
    assert run(tmp_path, data_dir, "--resume", config=grid(tmp_path, text)) == 1
    assert rec.calls == ["uniform", "bad reduction"]
    assert not (out / "uniform" / "failed.json").exists() and (out / "uniform" / "result.json").exists()
    assert table_rows(out)["uniform"][0] == "ok" and table_rows(out)["bad reduction"][0] == "failed"


def test_a_failing_rerun_replaces_the_old_result(tmp_path, data_dir, rec):
    assert run(tmp_path, data_dir) == 0
    rec.fail = {"dense"}
    assert run(tmp_path, data_dir, "--overwrite", "--only", "dense") == 1
    d = tmp_path / "out" / "dense"
    assert (d / "failed.json").exists() and not (d / "result.json").exists()
    assert table_rows(tmp_path / "out")["dense"][0] == "failed"


def test_corrupt_result_is_reported_and_rerun(tmp_path, data_dir, rec, capsys):
    assert run(tmp_path, data_dir) == 0
    res = tmp_path / "out" / "dense" / "result.json"
    res.write_text(res.read_text()[: len(res.read_text()) // 2])  # a half-written file (killed run)
    rec.calls.clear()
    capsys.readouterr()
    assert run(tmp_path, data_dir, "--resume") == 0 and rec.calls == ["dense"]
    out = capsys.readouterr().out
    assert "dense: replacing corrupt result (unreadable" in out and "JSONDecodeError" in out
    assert json.loads(res.read_text())["status"] == "ok"


def test_legacy_result_without_provenance_is_not_reused(tmp_path, data_dir, rec, capsys):
    assert run(tmp_path, data_dir) == 0
    res = tmp_path / "out" / "sparse-vw" / "result.json"
    legacy = json.loads(res.read_text())
    del legacy["provenance"]
    res.write_text(json.dumps(legacy))
    capsys.readouterr()
    assert run(tmp_path, data_dir, "--resume") == 2
    assert "'sparse (VW)' (no provenance recorded (written by an older smdm-plugin))" in capsys.readouterr().err
    assert run(tmp_path, data_dir, "--overwrite", "--only", "sparse (VW)") == 0
    assert "provenance" in json.loads(res.read_text())


def test_interrupted_run_keeps_finished_variants_and_resumes(tmp_path, data_dir, rec, capsys):
    rec.interrupt_at = "sparse (VW)"
    assert run(tmp_path, data_dir) == 130
    assert "interrupted" in capsys.readouterr().err
    out = tmp_path / "out"
    assert (out / "dense" / "result.json").exists() and not (out / "sparse-vw" / "result.json").exists()
    assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]
    rows = table_rows(out)
    assert rows["dense"][0] == "ok" and rows["sparse (VW)"][0] == "not run" and rows["uniform"][0] == "not run"
    rec.interrupt_at, rec.calls = None, []
    assert run(tmp_path, data_dir, "--resume") == 0 and rec.calls == ["sparse (VW)", "uniform"]


def test_out_that_is_a_file_or_a_foreign_folder_is_refused(tmp_path, data_dir, rec, capsys):
    out = tmp_path / "out"
    out.write_text("mine")
    assert run(tmp_path, data_dir) == 2 and "is not a folder" in capsys.readouterr().err
    assert out.read_text() == "mine"
    out.unlink()
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    for flags in ((), ("--resume",)):
        assert run(tmp_path, data_dir, *flags) == 2
        assert "non-empty folder without smdm ablate results" in capsys.readouterr().err
    assert rec.calls == []
    assert run(tmp_path, data_dir, "--overwrite") == 0 and (out / "notes.txt").read_text() == "mine"


def test_quick_grid_on_real_motion(hml_dir, tmp_path, monkeypatch):
    out = tmp_path / "abl"
    args = ["--config", str(QUICK), "--out", str(out), "--data", str(hml_dir), "--no-progress"]
    assert ablate.main(args) == 0
    md = (out / "results.md").read_text()
    for name in ("dense", "sparse (VW)", "w/o interpolation", "FSQ off"):
        assert f"| {name} | ok |" in md
    assert (out / "results.csv").exists() and (out / "loss_curves.png").stat().st_size > 0
    assert (out / "config.yaml").exists() and (out / "dense" / "config.json").exists()
    res = json.loads((out / "sparse-vw" / "result.json").read_text())
    dense = json.loads((out / "dense" / "result.json").read_text())
    assert res["keyframe_error_mm"] > 0 and dense["keyframe_error_mm"] is None
    assert len(res["losses"]) == 3 and res["ees"] is not None
    # jitter and foot skating of the samples, and of the real validation motions as a reference row
    for r in (res, dense):
        assert np.isfinite(r["jitter"]) and r["jitter"] > 0 and 0 <= r["foot_skating"] <= 1
    header = next(ln for ln in md.splitlines() if ln.startswith("| variant |"))
    assert "| jitter (m/s³) | foot skating |" in header
    cols = [c.strip() for c in header.strip("|").split("|")]
    ref = table_rows(out, reference=True)[report.REFERENCE_ROW]
    jit, skate = float(ref[cols.index("jitter (m/s³)") - 1]), float(ref[cols.index("foot skating") - 1])
    assert jit > 0 and 0 <= skate <= 1 and ref[0] == "reference"
    assert 0 < res["val_loss"] < 100 and 0 < dense["val_loss"] < 100  # same fixed noise and timesteps
    assert res["provenance"]["steps"] == 3 and res["provenance"]["settings"]["sparse_config"]["reduction"] == 0.8

    # resumed: nothing runs again; a crash of one rerun variant is recorded, the others survive
    calls = []
    real = ablate.run_variant

    def flaky(cfg, variant, *a, **k):
        calls.append(variant["name"])
        if variant["name"] == "FSQ off":
            raise RuntimeError("boom")
        return real(cfg, variant, *a, **k)

    monkeypatch.setattr(ablate, "run_variant", flaky)
    assert ablate.main(args + ["--resume"]) == 0 and calls == []
    assert ablate.main(args + ["--overwrite", "--only", "FSQ off"]) == 1 and calls == ["FSQ off"]
    assert "boom" in json.loads((out / "fsq-off" / "failed.json").read_text())["error"]
    md = (out / "results.md").read_text()
    assert "| FSQ off | failed |" in md and "| dense | ok |" in md


def test_missing_data_is_a_clear_message(tmp_path, capsys):
    (tmp_path / "d").mkdir()  # not tmp_path itself: an --out inside --data is refused as overlapping
    rc = ablate.main(["--config", str(QUICK), "--out", str(tmp_path / "x"), "--data", str(tmp_path / "d")])
    assert rc == 2 and "is not a HumanML3D-format folder (missing Mean.npy" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        ablate.main(["--config", str(QUICK), "--out", str(tmp_path / "x"), "--data", str(tmp_path / "none")])
    assert e.value.code == 2 and "argument --data: no such folder" in capsys.readouterr().err
