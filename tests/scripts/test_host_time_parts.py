"""scripts/host_time_parts.py: the meter's trans_enc cells with parts of the recipe switched off."""
import re
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "host_time_parts.py"


def test_it_prints_one_row_per_part_with_four_ratios():
    r = subprocess.run([sys.executable, str(SCRIPT), "--repeats", "2"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    rows = [l for l in r.stdout.splitlines() if l.startswith("| ") and "---" not in l][1:]
    assert [l.split("|")[1].strip() for l in rows] == ["the recipe", "no FSQ keys", "no Lipschitz layers", "neither"]
    for l in rows:
        assert len(re.findall(r"\d+\.\d\d", l)) == 4


def test_the_parts_reach_the_sparse_model():
    """``host_cells``' config is the one the sparse model is made with (the parts are not lost)."""
    from smdm_plugin.core.config import SparseConfig
    from smdm_plugin.core.checks import static_mode
    from smdm_plugin.training import hosttime

    counts = []
    for changes in ({}, {"fsq": False}, {"lipschitz": False}):
        with static_mode():
            train = hosttime.host_cells("trans_enc", True, "fp32", SparseConfig(**changes))["train"]
        names = dict(zip(train.__code__.co_freevars, train.__closure__))
        opt = names["opt"].cell_contents                      # the optimizer of the sparse model
        counts.append(sum(len(g["params"]) for g in opt.param_groups))
    assert counts[0] > counts[1] and counts[0] > counts[2]


def test_the_optimizer_rows_count_the_optimizer_step_inside_the_training_step():
    """``--optimizer``: the training step and its optimizer step alone, dense and sparse; the optimizer
    step is part of the training step (fewer frames) and steps more tensors for the sparse model."""
    r = subprocess.run([sys.executable, str(SCRIPT), "--optimizer", "--repeats", "2"], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    rows = [l.split("|")[1:-1] for l in r.stdout.splitlines() if l.startswith("| ") and "---" not in l][1:]
    assert [c[0].strip() for c in rows] == ["training step", "its optimizer step"]
    (train_d, train_s), (step_d, step_s) = [(int(c[1]), int(c[2])) for c in rows]
    assert step_d < train_d and step_s < train_s and step_s > step_d
    for c in rows:
        assert all(float(v) > 0 for v in c[3:])
