"""scripts/decisive_paired.py: per-seed paired differences (sparse − dense) with t-intervals, and the
CLI's rules for its input (one line naming the file and what was expected, exit 2)."""
import json
import os
import subprocess
import sys

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
METRICS = {"fid": 0.0, "r_precision_top1": 0.1, "r_precision_top3": 0.25, "matching_score": 5.0,
           "jitter_per_speed": 100.0, "jitter": 80.0, "speed": 0.7, "foot_skating": 0.1}


def _run(seed, fid, at=300.0):
    return {"seed": seed, "status": "ok", "snapshots": [
        {"kind": "seconds", "at": at, "step": 10 * (seed + 1), **METRICS, "fid": fid}]}


def _results(**config):
    dense = [_run(0, 10.0), _run(1, 12.0), _run(2, 14.0), _run(3, 99.0)]
    sparse = [_run(0, 8.0), _run(1, 11.0), _run(2, 11.0)]           # differences -2, -1, -3
    return {"config": {"name": "toy", "diffusion_steps": 10, **config}, "reference": {"fid_train_vs_eval": 30.0},
            "runs": {"dense": dense, "sparse (VW)": sparse}}


def _script(folder):
    return subprocess.run([sys.executable, os.path.join(REPO, "scripts", "decisive_paired.py"), str(folder)],
                          capture_output=True, text=True, env={**os.environ, "PYTHONPATH": REPO})


def test_paired_differences_and_intervals(tmp_path):
    """Three seeds of dense and sparse, one seed only dense: the pairs are the three shared seeds,
    the difference is the mean of the per-seed differences, the half-width t(0.975, 2)·sd/√3."""
    (tmp_path / "results.json").write_text(json.dumps(_results()))
    res = _script(tmp_path)
    assert res.returncode == 0, res.stderr
    assert "seeds [0, 1, 2] paired (3;" in res.stdout
    row = next(line for line in res.stdout.splitlines() if line.startswith("| 300 s cpu | FID"))
    hw = 4.303 * 1.0 / 3 ** 0.5                                      # sd of (-2, -1, -3) is 1
    assert f"| 12.00 | 10.00 | -2.00 ± {hw:.2f} | -2.00, -1.00, -3.00 |" in row, row


def test_primary_endpoints_get_bonferroni_intervals_and_holm(tmp_path):
    """A pre-registered endpoint is listed first, its interval Bonferroni-wide (one endpoint: the 95% one)."""
    (tmp_path / "results.json").write_text(json.dumps(_results(primary={"seconds": [300.0], "metrics": ["fid"]})))
    out = _script(tmp_path).stdout
    assert "Primary endpoints (pre-registered; 1 tests)" in out
    first = next(line for line in out.splitlines() if line.startswith("| 300 s cpu"))
    assert "| FID ↓ |" in first


@pytest.mark.parametrize("content, says", [
    ("{}", "has no 'config', 'runs', 'reference'"),
    ("[1, 2]", "holds a list; expected a JSON object"),
    ("not json", "not readable as JSON"),
    (None, "fid is null; expected a number"),
])
def test_bad_results_files_are_one_line_exit_2(tmp_path, content, says):
    if content is None:
        bad = _results()
        bad["runs"]["dense"][1]["snapshots"][0]["fid"] = None
        content = json.dumps(bad)
    (tmp_path / "results.json").write_text(content)
    res = _script(tmp_path)
    assert res.returncode == 2, res
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr
    assert str(tmp_path / "results.json") in res.stderr and says in res.stderr, res.stderr


def test_a_missing_results_file_is_one_line_exit_2(tmp_path):
    res = _script(tmp_path)
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "results.json" in res.stderr
    assert "no such file" in res.stderr
