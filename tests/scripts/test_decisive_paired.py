"""scripts/decisive_paired.py: per-seed paired differences (sparse − dense) with t-intervals."""
import json
import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _run(seed, fid, at=300.0):
    return {"seed": seed, "status": "ok", "snapshots": [
        {"kind": "seconds", "at": at, "step": 10 * (seed + 1), "fid": fid, "r_precision_top3": 0.25,
         "matching_score": 5.0, "jitter_per_speed": 100.0, "foot_skating": 0.1}]}


def test_paired_differences_and_intervals(tmp_path):
    """Three seeds of dense and sparse, one seed only dense: the pairs are the three shared seeds,
    the difference is the mean of the per-seed differences, the half-width t(0.975, 2)·sd/√3."""
    dense = [_run(0, 10.0), _run(1, 12.0), _run(2, 14.0), _run(3, 99.0)]
    sparse = [_run(0, 8.0), _run(1, 11.0), _run(2, 11.0)]           # differences -2, -1, -3
    results = {"config": {"name": "toy", "diffusion_steps": 10}, "reference": {"fid_train_vs_eval": 30.0},
               "runs": {"dense": dense, "sparse (VW)": sparse}}
    (tmp_path / "results.json").write_text(json.dumps(results))
    res = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "decisive_paired.py"), str(tmp_path)],
                         capture_output=True, text=True, env={**os.environ, "PYTHONPATH": REPO})
    assert res.returncode == 0, res.stderr
    assert "seeds [0, 1, 2] (3 paired)" in res.stdout
    row = next(line for line in res.stdout.splitlines() if line.startswith("| 300 s cpu | FID"))
    hw = 4.303 * 1.0 / 3 ** 0.5                                      # sd of (-2, -1, -3) is 1
    assert f"| 12.000 | 10.000 | -2.000 ± {hw:.3f} | 30.000 |" in row, row


def test_a_missing_results_file_is_one_line(tmp_path):
    res = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "decisive_paired.py"), str(tmp_path)],
                         capture_output=True, text=True, env={**os.environ, "PYTHONPATH": REPO})
    assert res.returncode == 1 and res.stderr.count("\n") == 1 and "results.json" in res.stderr
