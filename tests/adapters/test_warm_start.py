"""Starting sparse from a dense model: the zero-shot wrap (preset zero_shot, wrap_dense) and the
warm start (warm_start: Lipschitz MLPs and FSQ keys fitted to the dense layers)."""
import pytest
import torch

from smdm_plugin import SparseConfig, TinyMDM, sparsify
from smdm_plugin.adapters.surgery import unsparsify
from smdm_plugin.adapters.warm import (adds_layers, diffusion_probe, fit_mlp_to_linear, is_dense_wrap, warm_start,
                                       wrap_dense)
from smdm_plugin.core.config import MARKER
from smdm_plugin.core.presets import load_preset
from smdm_plugin.core.noise import NOISE_STEP
from smdm_plugin.core.lipschitz import LipschitzMLP
from smdm_plugin.reference.simple_diffusion import SimpleDiffusion

KW = dict(latent_dim=32, ff_size=64, num_layers=2, dropout=0.0, cond_mode="no_cond")
D, N = 263, 40


def dense(arch="trans_enc", seed=0):
    torch.manual_seed(seed)
    return TinyMDM(arch=arch, **KW).eval()


def call(model, x, t):
    with torch.no_grad():
        return model(x, t, y={"mask": torch.ones(x.shape[0], 1, 1, x.shape[-1], dtype=torch.bool),
                               "lengths": torch.full((x.shape[0],), x.shape[-1])})


def inputs(seed=1):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(3, D, 1, N, generator=g), torch.tensor([3, 20, 45])


def test_zero_shot_preset_adds_no_layer():
    c = load_preset("zero_shot")
    assert c.enabled and not c.lipschitz and not c.fsq and not adds_layers(c) and c.reduction == 0.8
    assert adds_layers(load_preset("smdm_paper"))


@pytest.mark.parametrize("arch", ["trans_enc", "trans_dec"])
def test_wrap_keeps_every_weight_and_reduction_0_equals_dense(arch):
    ref = dense(arch)
    before = {k: v.clone() for k, v in ref.state_dict().items()}
    x, t = inputs()
    want = call(ref, x, t)
    model = wrap_dense(dense(arch), load_preset("zero_shot").replace(reduction=0.0))
    after = model.state_dict()
    assert set(after) - set(before) == {MARKER, NOISE_STEP}
    for k, v in before.items():
        assert torch.equal(after[k], v), k            # weights untouched
    assert is_dense_wrap(model)
    assert torch.allclose(call(model, x, t), want, atol=1e-5)
    sparse_out = call(wrap_dense(dense(arch)), x, t)      # 80% dropped: differs
    assert not torch.allclose(sparse_out, want, atol=1e-3)


def test_wrapped_model_loads_a_dense_state_dict_and_its_own():
    src = dense(seed=3)
    model = wrap_dense(dense(seed=0))
    model.load_state_dict(src.state_dict())           # dense weights into the wrapped model
    for k, v in src.state_dict().items():
        assert torch.equal(model.state_dict()[k], v)
    model.load_state_dict(model.state_dict())
    unsparsify(model)
    assert not is_dense_wrap(model)
    plain = sparsify(dense(), SparseConfig(lipschitz=False, fsq=False))
    with pytest.raises(RuntimeError):                 # a plain sparse model still refuses a dense state dict
        plain.load_state_dict(src.state_dict())


def test_wrap_refuses_a_config_with_new_layers():
    model = dense()
    with pytest.raises(ValueError, match="lipschitz"):
        wrap_dense(model, "smdm_paper")
    assert MARKER not in dict(model.named_buffers())


def test_fit_mlp_to_linear_reference():
    torch.manual_seed(0)
    for n_in, n_out, hidden in ((263, 32, 32), (32, 263, 32), (20, 30, 64), (40, 40, 16)):
        lin = torch.nn.Linear(n_in, n_out)
        mlp = LipschitzMLP(n_in, n_out, hidden=hidden, layers=3)
        x = torch.randn(500, n_in) * 2
        with torch.no_grad():
            err = fit_mlp_to_linear(mlp, lin, x)
            out, ref = mlp(x), lin(x)
        if hidden >= min(n_in, n_out):
            assert err.rel_rms < 2e-3, (n_in, n_out, err)
            assert torch.allclose(out, ref, atol=2e-3 * float(ref.abs().max()))
        else:                                          # rank-limited: as good as the best rank-`hidden` map
            U, S, Vh = torch.linalg.svd(lin.weight.detach())
            best = x @ (U[:, :hidden] * S[:hidden] @ Vh[:hidden]).T + lin.bias.detach()
            assert float((out - ref).norm()) <= 1.01 * float((best - ref).norm())
            assert float((best - ref).norm()) < 0.9 * float(ref.norm())    # (the reference is no trivial bound)


@pytest.mark.parametrize("fsq", [False, True])
def test_warm_start_reproduces_the_dense_model_at_reduction_0(fsq):
    ref = dense("trans_dec")
    x, t = inputs()
    want = call(ref, x, t)
    diffusion = SimpleDiffusion(50)
    model = dense("trans_dec")
    y = {"mask": torch.ones(3, 1, 1, N, dtype=torch.bool), "lengths": torch.full((3,), N)}
    probe = diffusion_probe(torch.randn(3, D, 1, N), {"y": y}, diffusion.q_sample, 50)
    cfg = SparseConfig(reduction=0.0, fsq=fsq)
    report = warm_start(model, cfg, probe)
    assert len(report.mlps) == 2 and all(e.rel_rms < 5e-3 for e in report.mlps), report
    got = call(model, x, t)
    rel = float((got - want).norm() / want.norm())
    if fsq:                                            # quantised keys: close, not equal
        assert len(report.fsq) == 2 and all(e.rel_rms < 0.6 for e in report.fsq), report
        assert rel < 0.1, rel
        cold = sparsify(dense("trans_dec"), cfg)       # FSQ + Lipschitz at random init
        assert rel < 0.5 * float((call(cold, x, t) - want).norm() / want.norm())
    else:
        assert rel < 1e-3, rel
    # the warm-started model is a plain sparse model: its state dict loads elsewhere with no flag
    other = sparsify(dense("trans_dec", seed=7), cfg)
    other.load_state_dict(model.state_dict())
    assert torch.allclose(call(other, x, t), got, atol=1e-6)


# ------------------------------------------------------------------- smdm train --init-from
def _train(hml_dir, out, *args):
    from smdm_plugin.apps import train as train_cli

    return train_cli.main(["--data", str(hml_dir), "--out", str(out), "--latent-dim", "32", "--layers", "2",
                           "--ff-size", "64", "--steps", "3", "--batch", "2", "--diffusion-steps", "10",
                           "--dropout", "0", "--no-progress", "--threads", "1", *args])


def test_smdm_train_init_from_warm_starts_and_records_the_origin(hml_dir, tmp_path, capsys):
    import json

    from smdm_plugin.adapters.warm import file_digest
    from smdm_plugin.io.humanml3d import load_humanml3d
    from smdm_plugin.training import trainer as T
    from smdm_plugin.training.data import MotionSet

    assert _train(hml_dir, tmp_path / "dense") == 0
    dense_model, _ = T.load_trained(str(tmp_path / "dense"))
    pt = sorted((tmp_path / "dense").glob("model*.pt"))[-1]
    # before any step: the warm-started sparse model at reduction 0 computes what the dense one does
    data = MotionSet.from_split(load_humanml3d(str(hml_dir), "train"))
    cfg = T.TrainConfig(steps=0, batch=2, diffusion_steps=10, model={"latent_dim": 32, "num_layers": 2,
                        "ff_size": 64, "dropout": 0.0}, sparse=SparseConfig(reduction=0.0, fsq=False))
    tr = T.Trainer(cfg, data, device="cpu", init_from=str(tmp_path / "dense"))
    x, t = inputs()
    want, got = call(dense_model.eval(), x, t), call(tr.model.eval(), x, t)
    assert float((got - want).norm() / want.norm()) < 1e-3
    assert tr.init_origin["digest"] == file_digest(str(pt)) and tr.init_origin["path"] == str(pt)
    # through the command: origin recorded, and the result loads with no flag
    capsys.readouterr()
    assert _train(hml_dir, tmp_path / "warm", "--sparse", "--init-from", str(tmp_path / "dense")) == 0
    assert "initialised from the dense checkpoint" in capsys.readouterr().out
    rec = json.loads((tmp_path / "warm" / "train_config.json").read_text())["init_from"]
    assert rec["digest"] == file_digest(str(pt)) and len(rec["fit"]["mlps"]) == 2
    model, config = T.load_trained(str(tmp_path / "warm"))
    assert config is not None and config.lipschitz and config.fsq


def test_smdm_train_init_from_refuses_bad_origins(hml_dir, tmp_path, capsys):
    assert _train(hml_dir, tmp_path / "sparse", "--sparse") == 0
    capsys.readouterr()
    assert _train(hml_dir, tmp_path / "w1", "--sparse", "--init-from", str(tmp_path / "sparse")) == 2
    assert "holds a sparse model" in capsys.readouterr().err
    assert _train(hml_dir, tmp_path / "w2", "--init-from", str(tmp_path / "nothing")) == 2
    assert "--init-from" in capsys.readouterr().err
    assert not (tmp_path / "w1").exists() and not (tmp_path / "w2").exists()
    with pytest.raises(SystemExit) as e:
        _train(hml_dir, tmp_path / "sparse", "--resume", "--init-from", str(tmp_path / "sparse"))
    assert e.value.code == 2


# ------------------------------------------------------------------- upstream options (no checkout)
def _mdm_like_parser():
    """The shape of MDM's parser: add_model_options(parser) adds a 'model' group and calls
    add_sparse_options(group), as patches/mdm.patch does."""
    import argparse

    from smdm_plugin.families.mdm.upstream import add_sparse_options

    def add_model_options(parser):
        group = parser.add_argument_group("model")
        group.add_argument("--layers", type=int, default=8)
        add_sparse_options(group)

    parser = argparse.ArgumentParser()
    add_model_options(parser)
    return parser


def test_start_options_are_not_in_the_model_group():
    p = _mdm_like_parser()
    a = p.parse_args(["--sparse_preset", "zero_shot", "--sparse_init_from", "x.pt"])
    assert a.sparse_preset == "zero_shot" and a.sparse_init_from == "x.pt"
    model = next(g for g in p._action_groups if g.title == "model")
    dests = {x.dest for x in model._group_actions}
    assert "sparse" in dests and "sparse_reduction" in dests                     # restored from args.json
    assert "sparse_preset" not in dests and "sparse_init_from" not in dests      # never restored
    assert "--sparse_preset" in p.format_help()


def test_resolve_wraps_only_dense_checkpoints_and_refuses_new_layers(capsys):
    import argparse

    from smdm_plugin.integrations.start import resolve

    dense = SparseConfig(enabled=False)
    s = resolve(argparse.Namespace(sparse_preset="zero_shot", sparse_init_from=None), dense, training=False)
    assert s.wrap and s.config.enabled and not s.config.lipschitz
    with pytest.warns(UserWarning, match="already sparse"):                 # a sparse checkpoint keeps its own
        s = resolve(argparse.Namespace(sparse_preset="zero_shot"), SparseConfig(), training=False)
    assert not s.wrap and s.config.lipschitz
    with pytest.raises(SystemExit) as e:
        resolve(argparse.Namespace(sparse_preset="smdm_paper"), dense, training=False)
    assert e.value.code == 2 and "no weights for" in capsys.readouterr().err
    s = resolve(argparse.Namespace(sparse_preset="smdm_paper", sparse_init_from=None), dense, training=True)
    assert not s.wrap and s.config.enabled and s.config.fsq                  # training: the run's settings
    with pytest.raises(SystemExit):
        resolve(argparse.Namespace(sparse_preset=None, sparse_init_from="nope.pt"), SparseConfig(), training=True)
