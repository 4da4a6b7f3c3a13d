"""smdm ablate's typed results: Status / CacheState / Action enums and the records they ride in.
The records on disk (result.json, failed.json) keep their format: a study running with the old
code resumes and reports with the new one."""
import json

import pytest

from smdm_plugin.apps.ablate.report import write_report
from smdm_plugin.apps.ablate.results import (CacheState, Cached, Status, failure_record, is_ok, read_cached,
                                             row_from_cache, status_of)
from smdm_plugin.apps.common.provenance import make_provenance


def test_status_reads_and_writes_as_its_string():
    assert Status.OK == "ok" and Status.NOT_RUN == "not run"
    assert json.dumps({"status": Status.FAILED}) == '{"status": "failed"}'
    assert str(Status.OK) == f"{Status.OK}" == "ok" and f"{Status.STALE:>6}" == " stale"
    assert status_of({"status": "ok"}) is Status.OK and is_ok({"status": "ok"})
    assert status_of({"status": "weird"}) is None and status_of(None) is None and not is_ok({})
    assert Cached("current").state is CacheState.CURRENT
    with pytest.raises(ValueError):
        Cached("nonsense")


def test_failure_record_keeps_the_format():
    try:
        raise RuntimeError("boom")
    except RuntimeError as e:
        study = failure_record("sparse (VW)", e, {"p": 1}, seed=3)
        ablate = failure_record("dense", e, {"p": 2}, wall_s=1.5)
    assert list(study) == ["name", "seed", "status", "error", "traceback", "provenance"]
    assert list(ablate) == ["name", "status", "error", "traceback", "wall_s", "provenance"]
    back = json.loads(json.dumps(study))
    assert back["status"] == "failed" and back["error"] == "RuntimeError: boom" and "boom" in back["traceback"]


@pytest.fixture
def prov():
    return make_provenance({"a": 1}, "fp", 10, 0, "cpu")


def test_read_cached_classifies_records_written_in_the_old_format(tmp_path, prov):
    """A result.json / failed.json with plain string statuses (what the running study writes)."""
    (tmp_path / "cur").mkdir()
    (tmp_path / "cur" / "result.json").write_text(json.dumps(
        {"name": "v", "seed": 0, "status": "ok", "steps": 10, "losses": [1.0, 0.5], "provenance": prov}))
    got = read_cached(str(tmp_path / "cur"), prov)
    assert got.state is CacheState.CURRENT and got.record["losses"] == [1.0, 0.5]
    other = make_provenance({"a": 2}, "fp", 10, 0, "cpu")
    stale = read_cached(str(tmp_path / "cur"), other)
    assert stale.state is CacheState.STALE and "settings" in stale.reason
    assert row_from_cache("v", stale) == {"name": "v", "status": Status.STALE, "reason": stale.reason}
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "result.json").write_text('{"status": "ok", "final_loss": "x"}')
    assert read_cached(str(tmp_path / "bad"), prov).state is CacheState.CORRUPT
    (tmp_path / "fail").mkdir()
    (tmp_path / "fail" / "failed.json").write_text(json.dumps({"name": "v", "status": "failed", "error": "E: x"}))
    failed = read_cached(str(tmp_path / "fail"), prov)
    assert failed.state is CacheState.FAILED and failed.reason == "E: x"
    assert row_from_cache("v", failed)["status"] is Status.FAILED
    assert read_cached(str(tmp_path / "none"), prov).state is CacheState.MISSING
    assert row_from_cache("v", Cached(CacheState.MISSING)) == {"name": "v", "status": "not run"}
    assert row_from_cache("v", got)["reused"] is True


def test_the_report_prints_statuses_as_words(tmp_path):
    cfg = {"name": "g", "steps": 1, "batch": 1, "seed": 0, "model": {}, "diffusion_steps": 1}
    rows = [{"name": "a", "status": Status.OK, "final_loss": 0.5, "losses": [1.0, 0.5]},
            {"name": "b", "status": Status.NOT_RUN}, {"name": "c", "status": Status.FAILED, "error": "E: x"}]
    text = write_report(rows, str(tmp_path), None, cfg)
    assert "| a | ok |" in text and "| b | not run |" in text and "Status." not in text
    assert "Not run yet: b." in text and "c failed: E: x" in text
    assert "Status." not in (tmp_path / "results.csv").read_text()
