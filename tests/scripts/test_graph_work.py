"""scripts/graph_work.py: the work in the graphs a ``--compile`` run captures, dense beside sparse."""
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "graph_work.py"


def test_a_sparse_sampling_graph_has_no_op_on_parameters_alone():
    r = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--variants", "trans_enc", "--precisions", "fp32",
                        "--calls", "sample", "train"], capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    rows = [[c.strip() for c in l.split("|")[1:-1]] for l in r.stdout.splitlines() if l.startswith("| trans_enc")]
    assert [row[2] for row in rows] == ["sample", "train"]
    sample, train = rows
    assert all(int(c) > 0 for c in sample[3:5] + sample[6:8]) and sample[8] == "0" and sample[5] == "0"
    assert train[5] == train[8] == "—" and int(train[6]) > 0
