"""scripts/time_src_mask.py: upstream's padding mask read from a checkout, timed beside the flag's."""
import re
import subprocess
import sys
from pathlib import Path

from helpers import upstream_mask

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "time_src_mask.py"

TRANSFORMER = upstream_mask.TRANSFORMER_SOURCE


def _run(*args):
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300)


def test_it_times_the_checkout_s_mask_beside_the_flag_s(tmp_path):
    models = tmp_path / "text2motion" / "models"
    models.mkdir(parents=True)
    (models / "transformer.py").write_text(TRANSFORMER)
    r = _run("--repo", str(tmp_path), "--batch", "4", "--frames", "60", "--repeats", "2")
    assert r.returncode == 0, r.stderr
    rows = [l for l in r.stdout.splitlines() if l.startswith("| ") and "---" not in l][1:]
    assert [l.split("|")[1].strip() for l in rows] == ["upstream's `generate_src_mask`", "the flag's `src_mask`"]
    assert all(re.search(r"\| \d+\.\d+ \|$", l) for l in rows)
    assert "B = 4, T = 60" in r.stdout


def test_a_folder_without_the_model_is_exit_2_naming_the_argument(tmp_path):
    r = _run("--repo", str(tmp_path))
    assert r.returncode == 2 and "argument --repo" in r.stderr.splitlines()[-1] and "Traceback" not in r.stderr
    models = tmp_path / "text2motion" / "models"
    models.mkdir(parents=True)
    (models / "transformer.py").write_text("class Other:\n    pass\n")
    r = _run("--repo", str(tmp_path))
    assert r.returncode == 2 and "no MotionTransformer.generate_src_mask" in r.stderr


def test_a_mask_that_differs_is_exit_1(tmp_path):
    models = tmp_path / "text2motion" / "models"
    models.mkdir(parents=True)
    # one frame more kept per sample than upstream's
    (models / "transformer.py").write_text(TRANSFORMER.replace("frame < int(n)", "frame <= int(n)"))
    r = _run("--repo", str(tmp_path), "--batch", "3", "--frames", "50", "--repeats", "1")
    assert r.returncode == 1 and "differs" in r.stderr, (r.returncode, r.stderr)
