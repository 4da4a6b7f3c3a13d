"""scripts/gpu_check.py (issue 36's one GPU check) runs on the CPU (``--dry-run``: tiny sizes,
``aot_eager``) and writes its one table between the markers of a copy of docs/gpu.md, leaving
the rest of the page as it was; cells that crash, miss the tolerance or were not run say so."""
import importlib.util
import re
import sys

import pytest
import torch

from helpers.paths import ROOT

pytest.importorskip("torch._dynamo")


def _script():
    spec = importlib.util.spec_from_file_location("gpu_check", ROOT / "scripts" / "gpu_check.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod                     # (its dataclasses look their module up)
    spec.loader.exec_module(mod)
    return mod


def test_docs_gpu_md_has_one_marked_section():
    text = (ROOT / "docs" / "gpu.md").read_text()
    gc = _script()
    assert text.count(gc.BEGIN) == 1 and text.count(gc.END) == 1 and text.index(gc.BEGIN) < text.index(gc.END)


def test_dry_run_writes_one_table_between_the_markers(tmp_path, capsys):
    gc = _script()
    doc = tmp_path / "gpu.md"
    original = (ROOT / "docs" / "gpu.md").read_text()
    doc.write_text(original)
    assert gc.main(["--dry-run", "--models", "trans_enc", "--precisions", "bf16", "--calls", "sample", "loop",
                    "--modes", "eager", "reduce-overhead", "--profile", "--doc", str(doc)]) == 0
    text = doc.read_text()
    before, rest = text.split(gc.BEGIN)
    block, after = rest.split(gc.END)
    old_before, old_rest = original.split(gc.BEGIN)
    assert before == old_before and after == old_rest.split(gc.END)[1]       # the lead's prose untouched
    lines = block.strip().splitlines()
    assert f"torch {torch.__version__}" in lines[0] and "triton" in lines[0]
    tables = [ln for ln in lines if ln.startswith("|")]
    assert tables[0].startswith("| model | precision | call | eager: check |")
    assert "reduce-overhead (ran default): check" in tables[0]              # no CUDA graphs on the CPU
    rows = tables[2:]
    assert [r.split(" | ")[:3] for r in rows] == [["| trans_enc", "bf16", "sampling call"],
                                                  ["| trans_enc", "bf16", "sampling loop"]]
    for r in rows:
        cells = [c.strip() for c in r.strip("|").split("|")]
        assert cells[3].startswith("ok ") and cells[7].startswith("ok "), r     # eager, reduce-overhead
        assert float(cells[4]) > 0 and float(cells[5]) > 0 and cells[6].endswith("×"), r
    printed = capsys.readouterr()
    assert block.strip() in printed.out                                      # printed too
    for call in ("sample", "loop"):                                          # what each compiled cell compiled (log)
        assert re.search(rf"compiled trans_enc bf16 {call} reduce-overhead: dense [1-9]\d* graph\(s\), 0 without CUDA "
                         r"graphs; sparse [1-9]\d* graph\(s\), 0 without CUDA graphs; while timed 0 compiled, "
                         r"0 CUDA-graph skips", printed.err), call
        for kind in ("dense", "sparse"):                                     # --profile: each model's call
            assert re.search(rf"profile trans_enc bf16 {call} reduce-overhead {kind}: host self \d+\.\d+ ms/call",
                             printed.err), (call, kind)
    assert "profile trans_enc bf16 sample eager" not in printed.err              # (compiled cells only)


def test_table_says_what_crashed_failed_or_did_not_run(tmp_path):
    gc = _script()
    s = gc.settings(gc.argparse.Namespace(dry_run=True, models=["trans_dec"], precisions=["fp32"], calls=["train"],
                                          modes=["eager", "default"], profile=False))
    row = gc.Row("trans_dec", "fp32", "train", check={"eager": "FAIL 2.0e-01 > 1e-03",
                                                      "default": "error: " + gc.one_line(RuntimeError("a | b\nmore"))},
                 speed={"eager": (2.0, 1.0)})
    block = gc.table(s, [row], gc.Clock(1.0), skipped=1)
    line = [ln for ln in block.splitlines() if ln.startswith("| trans_dec")][0]
    assert "| FAIL 2.0e-01 > 1e-03 | 2.00 | 1.00 | 2.00× |" in line
    assert "| error: RuntimeError: a / b | not run | — | — |" in line
    assert "1 check / speed cells not run" in block
    bare = tmp_path / "page.md"
    bare.write_text("# no markers\n")
    with pytest.raises(ValueError, match="gpu-check:begin"):
        gc.write_doc(str(bare), block)
