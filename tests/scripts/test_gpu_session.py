"""scripts/gpu_session.sh, the next GPU session's one call: valid bash, and every option it passes is
one its Python scripts accept (argparse reads them all before ``--help`` ends the run)."""
import importlib.util
import re
import shlex
import subprocess
import sys

import pytest

from helpers.paths import ROOT

SCRIPT = ROOT / "scripts" / "gpu_session.sh"


def _commands():
    text = SCRIPT.read_text().replace("\\\n", " ")
    for line in text.splitlines():
        m = re.search(r"python3 (scripts/\w+\.py)(.*)$", line)
        if m:
            args = [a for a in shlex.split(m.group(2)) if not a.startswith('"${') and a != "${diag[@]}"]
            yield m.group(1), [a.replace("$OUT", "out") for a in args if "dry[@]" not in a and "diag[@]" not in a]


def test_the_session_script_is_valid_bash():
    assert subprocess.run(["bash", "-n", str(SCRIPT)], capture_output=True).returncode == 0


def test_every_option_the_session_passes_is_accepted(capsys, monkeypatch):
    commands = list(_commands())
    assert {c for c, _ in commands} == {"scripts/gpu_diagnose.py", "scripts/gpu_check.py"} and len(commands) == 5
    for path, args in commands:
        spec = importlib.util.spec_from_file_location(path.replace("/", "_")[:-3], ROOT / path)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = mod
        spec.loader.exec_module(mod)
        for extra in ([], ["--dry-run"]):
            monkeypatch.setattr(sys, "argv", [path, *args, *extra, "--help"])
            with pytest.raises(SystemExit) as e:
                mod.main(sys.argv[1:]) if path.endswith("gpu_check.py") else mod.main()
            assert e.value.code == 0, (path, args, capsys.readouterr().err)


def test_every_table_the_session_writes_into_is_copied_first():
    """``gpu_check.py --doc`` rewrites an existing doc (the H200 session's captured step stopped at
    once when its copy was missing): each ``--doc "$OUT/NAME"`` has a ``cp docs/gpu.md "$OUT/NAME"``
    before it."""
    text = SCRIPT.read_text()
    docs = re.findall(r'--doc "\$OUT/([\w.]+)"', text)
    assert len(docs) == 2
    for name in docs:
        copy = text.find(f'cp docs/gpu.md "$OUT/{name}"')
        assert 0 <= copy < text.find(f'--doc "$OUT/{name}"'), name
