"""`smdm bench --quick` smoke run, `python -m smdm_plugin.apps.bench keyframes`, and the `smdm` CLI."""
import json
import subprocess
import sys
import types

from smdm_plugin.apps import bench, cli


def test_bench_quick_writes_json_and_table(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert bench.main(["--quick", "--arch", "trans_enc", "trans_dec", "--reductions", "0.8", "--out", str(out)]) == 0
    r = json.loads(out.read_text())
    rows = {(x["arch"], x["mode"], x["variant"]) for x in r["rows"]}
    assert ("trans_enc", "train", "dense") in rows and ("trans_dec", "sample", "sparse 80%") in rows
    sparse = [x for x in r["rows"] if x["variant"] != "dense"]
    assert all(x["speedup"] > 0 and 0 <= x["overhead_share"] and x["peak_mem_mib"] >= 0 for x in sparse)
    assert "| trans_enc | train | dense |" in capsys.readouterr().out
    assert out.with_suffix(".md").exists()


def test_bench_keyframes_module_mode():
    p = subprocess.run([sys.executable, "-m", "smdm_plugin.apps.bench", "keyframes", "--repeats", "1"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and "batched VW on [64, 196, 64]" in p.stdout


def test_cli_help_and_run_delegates(monkeypatch, capsys):
    assert cli.main(["--help"]) == 0 and "bench" in capsys.readouterr().out
    assert cli.main(["nope"]) == 2
    seen = []
    fake = types.ModuleType("smdm_plugin.integrations.launcher")
    fake.main_run = lambda argv: seen.append(argv) or 0
    monkeypatch.setitem(sys.modules, "smdm_plugin.integrations.launcher", fake)
    import smdm_plugin.integrations as integ

    monkeypatch.setattr(integ, "launcher", fake, raising=False)
    assert cli.main(["run", "mdm", "--", "-m", "sample.generate"]) == 0
    assert seen == [["mdm", "--", "-m", "sample.generate"]]
