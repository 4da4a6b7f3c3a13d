"""`smdm bench`: the quick smoke run, its outputs, and what a user gets for bad or repeated input
(one line, exit 2, no traceback, nothing overwritten)."""
import json
import subprocess
import sys
import types

import pytest
import torch

from smdm_plugin.apps import bench, cli
from smdm_plugin.training import benchmark, timing, workloads


def smdm(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "smdm_plugin", *args], capture_output=True, text=True,
                          timeout=timeout)


def test_bench_quick_writes_json_and_table(tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert bench.main(["--quick", "--arch", "trans_enc", "trans_dec", "--reductions", "0.8", "--modes", "train",
                       "sample", "loop", "--steps", "4", "--out", str(out)]) == 0
    r = json.loads(out.read_text())
    rows = {(x["arch"], x["mode"], x["variant"]) for x in r["rows"]}
    assert ("trans_enc", "train", "dense") in rows and ("trans_dec", "sample", "sparse 80%") in rows
    assert ("trans_enc", "loop", "sparse 80%") in rows
    sparse = [x for x in r["rows"] if x["variant"] != "dense"]
    assert all(x["speedup"] > 0 and x["peak_mem_mib"] >= 0 for x in sparse)
    assert all(0 <= x["overhead_share"] for x in sparse if x["mode"] != "loop")
    assert r["sparse_backend"] == "varlen" and r["amp"] == "fp32" and r["compile"] == "none"
    assert all(isinstance(x["launches"], int) and x["launches"] > 0 for x in r["rows"])   # eager: counted
    text = capsys.readouterr().out
    assert "| trans_enc | train | eager | dense |" in text and "sparse attention backend: varlen" in text
    assert "| launches |" in text
    assert out.with_suffix(".md").read_text().startswith("device:")


def test_bench_bf16_and_compiled_modes_run():
    r = benchmark.run_bench(["trans_enc"], [0.8], batch=2, frames=24, repeats=1, warmup=1, device="cpu", quick=True,
                        steps=4, modes=["train", "sample"], amp="bf16", compile_mode="default")
    assert {x["variant"] for x in r["rows"]} == {"dense", "sparse 80%"} and r["sparse_backend"] == "compact"
    assert "torch.compile default" in bench.markdown(r) and "bf16" in bench.markdown(r)
    assert all(x["launches"] is None for x in r["rows"])          # compiled on the CPU: nothing to count


def test_bench_several_compile_modes_one_table(capsys):
    """``--compile none reduce-overhead``: both sides at both modes in one table; without CUDA
    reduce-overhead runs as default and the table says so; launches counted for eager cells, and
    the sparse step launches fewer kernels per frame... at least as few as the counter says for its
    own eager run (the counter is deterministic: a second count agrees)."""
    assert bench.main(["--quick", "--arch", "trans_enc", "--reductions", "0.8", "--modes", "sample", "--steps", "4",
                       "--device", "cpu", "--compile", "none", "reduce-overhead"]) == 0
    text = capsys.readouterr().out
    rows = [ln for ln in text.splitlines() if ln.startswith("| trans_enc | sample |")]
    assert len(rows) == 4
    assert sum("| eager |" in ln for ln in rows) == 2
    assert sum("torch.compile default (asked reduce-overhead)" in ln for ln in rows) == 2
    assert "eager and torch.compile reduce-overhead" in text


def test_bench_times_dip_and_doubletake_on_request(capsys):
    """``--arch dip doubletake``: DiP's prefix completion (40 frames after 20) and priorMDM's
    DoubleTake model (its first take's handshake frames forced at sampling); not by default."""
    assert bench.main(["--quick", "--arch", "dip", "doubletake", "--reductions", "0.8", "--modes", "train", "sample",
                       "--steps", "4", "--device", "cpu"]) == 0
    text = capsys.readouterr().out
    for arch in ("dip", "doubletake"):
        assert f"| {arch} | train | eager | sparse 80% |" in text and f"| {arch} | sample | eager | dense |" in text
    assert workloads.WORKLOADS.get("mdm").default_archs == ("trans_enc", "trans_dec")


def test_launch_count_of_an_eager_cell_is_the_counters():
    from smdm_plugin.runtime.launches import count_launches

    model, diffusion = workloads.build("trans_enc", 0.8, torch.device("cpu"), True, 4)
    data = workloads.WORKLOADS.get("mdm").batch(2, 24, torch.device("cpu"), True)
    fn = benchmark.step_fn("sample", workloads.WORKLOADS.get("mdm"), model, diffusion, data, torch.device("cpu"))
    fn()
    assert timing.launches(fn, torch.device("cpu"), False) == count_launches(fn, warmup=0).count > 0


def test_bench_rejects_unknown_compile_modes():
    p = smdm("bench", "--quick", "--compile", "max")
    assert p.returncode == 2 and "--compile" in p.stderr and "Traceback" not in p.stderr


@pytest.mark.parametrize("fsq,dense_fsq,sparse_fsq", [("paper", False, True), ("both", True, True),
                                                     ("off", False, False)])
def test_fsq_choice_decides_which_side_gets_fsq_keys(fsq, dense_fsq, sparse_fsq):
    from smdm_plugin.core.fsq import FSQMultiheadAttention

    def has_fsq(model):
        return any(isinstance(m, FSQMultiheadAttention) for m in model.modules())

    dense, _ = workloads.build("trans_enc", None, torch.device("cpu"), True, 4, fsq=fsq)
    sparse, _ = workloads.build("trans_enc", 0.8, torch.device("cpu"), True, 4, fsq=fsq)
    assert (has_fsq(dense), has_fsq(sparse)) == (dense_fsq, sparse_fsq)
    assert sparse._smdm_state.config.fsq is sparse_fsq


def test_bench_keyframes_module_mode():
    p = subprocess.run([sys.executable, "-m", "smdm_plugin.apps.bench", "keyframes", "--repeats", "1"],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and "VW keyframe selection on [64, 196, 64]" in p.stdout


@pytest.mark.parametrize("args,message", [
    (["--batch", "0"], "argument --batch: must be an integer in [1, 65536], got 0"),
    (["--frames", "1"], "argument --frames: must be an integer in [2, 4096], got 1"),
    (["--reductions", "1.0"], "argument --reductions: must be a finite number in [0, 1), got 1.0"),
    (["--repeats", "x"], "argument --repeats: expected an integer, got 'x'"),
    (["--steps", "-3"], "argument --steps: must be an integer >= 1, got -3"),
])
def test_bad_numbers_are_one_line_errors(args, message):
    p = smdm("bench", *args)
    assert p.returncode == 2 and message in p.stderr and "Traceback" not in p.stderr


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_a_device_that_does_not_exist_is_a_one_line_error():
    p = smdm("bench", "--device", "cuda")
    assert p.returncode == 2 and "argument --device: cuda: CUDA is not available" in p.stderr
    assert "Traceback" not in p.stderr


def test_outputs_are_never_overwritten_without_asking(tmp_path):
    md = tmp_path / "table.md"
    md.write_text("my notes\n")
    p = smdm("bench", "--quick", "--arch", "trans_enc", "--modes", "sample", "--reductions", "0.8", "--out", str(md))
    assert p.returncode == 2 and "--overwrite" in p.stderr and md.read_text() == "my notes\n"
    assert not (tmp_path / "table.json").exists()
    p = smdm("bench", "--quick", "--arch", "trans_enc", "--modes", "sample", "--reductions", "0.8", "--out", str(md),
             "--overwrite")
    assert p.returncode == 0, p.stderr
    assert json.loads((tmp_path / "table.json").read_text())["rows"] and md.read_text().startswith("device:")


def test_quick_never_overrides_a_flag_the_user_gave(tmp_path):
    out = tmp_path / "q"
    p = smdm("bench", "--quick", "--batch", "3", "--frames", "30", "--arch", "trans_enc", "--modes", "sample",
             "--reductions", "0.8", "--out", str(out))
    assert p.returncode == 0, p.stderr
    r = json.loads((tmp_path / "q.json").read_text())
    assert r["batch"] == 3 and r["frames"] == 30 and r["repeats"] == 1


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


# ----------------------------------------------------------------------------- --family motiondiffuse
def test_bench_motiondiffuse_prints_dense_and_sparse_rows(tmp_path, capsys):
    out = tmp_path / "md.json"
    assert bench.main(["--quick", "--family", "motiondiffuse", "--reductions", "0.8", "--modes", "train", "sample",
                       "loop", "--steps", "3", "--frames", "48", "--out", str(out)]) == 0
    r = json.loads(out.read_text())
    rows = {(x["arch"], x["mode"], x["variant"]) for x in r["rows"]}
    assert rows == {("motiondiffuse", m, v) for m in ("train", "sample", "loop") for v in ("dense", "sparse 80%")}
    assert r["family"] == "motiondiffuse" and r["fsq"] == "off" and "MotionDiffuseDenoiser" in r["model_source"]
    assert all(x["speedup"] > 0 for x in r["rows"]) and all("overhead_share" in x for x in r["rows"]
                                                              if x["variant"] != "dense" and x["mode"] != "loop")
    text = capsys.readouterr().out
    assert "| motiondiffuse | train | eager | dense |" in text and "| motiondiffuse | sample | eager | sparse 80% |" in text
    assert "model family: motiondiffuse" in text and "FSQ keys: n/a" in text


def test_bench_models_come_from_the_family_registry():
    from smdm_plugin.adapters.families import FAMILIES, family_for
    from smdm_plugin.adapters.surgery import is_sparse

    assert workloads.family_choices() == [n for n in FAMILIES.names() if n in ("mdm", "motiondiffuse")]
    for family in workloads.family_choices():
        arch = workloads.WORKLOADS.get(family).archs[0]
        dense, _ = workloads.build(arch, None, torch.device("cpu"), True, 4, family=family, frames=40)
        sparse, _ = workloads.build(arch, 0.8, torch.device("cpu"), True, 4, family=family, frames=40)
        assert family_for(dense).name == family and not is_sparse(dense)
        assert is_sparse(sparse) and sparse._smdm_state.family.name == family


def test_bench_motiondiffuse_takes_the_upstream_class_from_root(tmp_path):
    models = tmp_path / "md" / "text2motion" / "models"
    models.mkdir(parents=True)
    (models / "__init__.py").write_text("")
    (models / "transformer.py").write_text(
        "from smdm_plugin.reference.motiondiffuse_denoiser import MotionDiffuseDenoiser as _Base\n\n\n"
        "class MotionTransformer(_Base):\n    pass\n")
    from smdm_plugin.families.motiondiffuse.workload import upstream_motion_transformer
    cls = upstream_motion_transformer(str(tmp_path / "md"))
    assert cls.__module__ == "models.transformer"
    model, _ = workloads.build("motiondiffuse", 0.8, torch.device("cpu"), True, 4, family="motiondiffuse", frames=40,
                           root=str(tmp_path / "md"))
    assert type(model) is cls and model._smdm_state.family.name == "motiondiffuse"


@pytest.mark.parametrize("args,message", [
    (["--family", "nope"], "argument --family: invalid choice: 'nope' (choose from 'mdm', 'motiondiffuse')"),
    (["--family", "motiondiffuse", "--arch", "trans_dec"], "argument --arch: 'trans_dec' is an MDM architecture"),
    (["--family", "motiondiffuse", "--fsq", "both"], "argument --fsq: --family motiondiffuse has no softmax"),
    (["--family", "motiondiffuse", "--root", "."], "argument --root: . is not a MotionDiffuse checkout"),
    (["--root", "."], "argument --root: --family mdm has no upstream model to load"),
    # a setting that cannot apply (0.10.5 ran and recorded it): the fast path never runs under autograd
    (["--fastpath", "--modes", "train"], "argument --fastpath: torch's fast path runs only without autograd"),
])
def test_bad_family_options_are_one_line_errors(args, message):
    p = smdm("bench", *args)
    assert p.returncode == 2 and message in p.stderr and "Traceback" not in p.stderr
    assert len([ln for ln in p.stderr.splitlines() if "error:" in ln]) == 1
