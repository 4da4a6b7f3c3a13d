import json

import pytest
import torch

from smdm_plugin import SparseConfig, TinyMDM, load_checkpoint, save_sparse_config, sparsify
from smdm_plugin.io.checkpoint_files import check_state_dict
from smdm_plugin.io.checkpoint_files import find_sparse_config

KW = dict(latent_dim=32, ff_size=64, num_layers=1)


def save_run(tmp_path, sparse: bool, with_config: bool = True):
    torch.manual_seed(0)
    model = TinyMDM(**KW)
    if sparse:
        sparsify(model, SparseConfig(reduction=0.7))
        if with_config:
            save_sparse_config(model, str(tmp_path))
    torch.save(model.state_dict(), tmp_path / "model000001.pt")
    (tmp_path / "backbone.json").write_text(json.dumps(KW))
    return model


def test_roundtrip_recreates_sparse_model(tmp_path):
    model = save_run(tmp_path, sparse=True)
    loaded, config = load_checkpoint(str(tmp_path / "model000001.pt"))
    assert config == model._smdm_state.config and loaded._smdm_state.config.reduction == 0.7
    x, t = torch.randn(2, 263, 1, 30), torch.tensor([1, 2])
    y = {"text_embed": torch.randn(1, 2, 512)}
    with torch.no_grad():
        assert torch.equal(loaded.eval()(x, t, y), model.eval()(x, t, y))


def test_mdm_args_json_is_enough(tmp_path):
    model = save_run(tmp_path, sparse=True, with_config=False)
    (tmp_path / "args.json").write_text(json.dumps({"arch": "trans_enc", **model._smdm_state.config.to_args_dict()}))
    assert find_sparse_config(str(tmp_path / "model000001.pt")) == model._smdm_state.config
    loaded, _ = load_checkpoint(str(tmp_path / "model000001.pt"))
    assert hasattr(loaded, "_smdm_state")


def test_sparse_checkpoint_without_config_is_a_clear_error(tmp_path):
    save_run(tmp_path, sparse=True, with_config=False)
    with pytest.raises(RuntimeError, match="no sparse config beside it"):
        load_checkpoint(str(tmp_path / "model000001.pt"))


def test_sparse_into_dense_and_dense_into_sparse_are_errors(tmp_path):
    sparse = save_run(tmp_path, sparse=True)
    with pytest.raises(RuntimeError, match="SPARSE .* dense"):
        check_state_dict(TinyMDM(**KW), sparse.state_dict())
    with pytest.raises(RuntimeError, match="DENSE model but the model is sparse"):
        check_state_dict(sparse, TinyMDM(**KW).state_dict())


def test_dense_checkpoint_loads_dense(tmp_path):
    save_run(tmp_path, sparse=False)
    model, config = load_checkpoint(str(tmp_path / "model000001.pt"))
    assert config is None and not hasattr(model, "_smdm_state")


def test_save_config_never_overwrites_unasked(tmp_path):
    save_sparse_config(SparseConfig(reduction=0.6), str(tmp_path))
    p = tmp_path / "sparse_config.json"
    before = p.read_bytes()
    with pytest.raises(FileExistsError, match=r"sparse_config.json' exists with another config \(differs in "
                                              r"reduction, fsq\); pass overwrite=True"):
        save_sparse_config(SparseConfig(reduction=0.7, fsq=False), str(tmp_path))  # the default: never overwrite
    assert p.read_bytes() == before
    # the same config again (a second save, every rank of a distributed run): nothing to refuse
    assert save_sparse_config(SparseConfig(reduction=0.6), str(tmp_path)) == str(p) and p.read_bytes() == before
    p.write_text("{ half-writ")
    with pytest.raises(FileExistsError, match="exists with contents that are not a valid config"):
        save_sparse_config(SparseConfig(reduction=0.6), str(tmp_path))
    assert save_sparse_config(SparseConfig(reduction=0.7), str(tmp_path), overwrite=True) == str(p)
    assert SparseConfig.load(p).reduction == 0.7 and sorted(x.name for x in tmp_path.iterdir()) == [p.name]
    with pytest.raises(ValueError, match="not sparse"):
        save_sparse_config(TinyMDM(**KW), str(tmp_path / "new"))
    assert save_sparse_config(SparseConfig(), str(tmp_path / "a" / "b")).endswith("a/b/sparse_config.json")


@pytest.mark.parametrize("change,fields", [
    ({"reduction": 0.8}, ["reduction: saved 0.7, model 0.8"]),
    ({"fsq": False}, ["fsq: saved True, model False"]),
    ({"reduction": 0.9, "lipschitz": False, "selector": "uniform"},
     ["reduction: saved 0.7, model 0.9", "selector: saved 'vw', model 'uniform'", "lipschitz: saved True, model False"]),
])
def test_sparse_model_with_another_config_is_a_clear_error(tmp_path, change, fields):
    save_run(tmp_path, sparse=True)
    other = sparsify(TinyMDM(**KW), SparseConfig(reduction=0.7).replace(**change))
    with pytest.raises(ValueError) as e:
        load_checkpoint(str(tmp_path / "model000001.pt"), model=other)
    msg = str(e.value)
    assert f"in {len(fields)} field(s)" in msg and str(tmp_path / "sparse_config.json") in msg
    for f in fields:
        assert f in msg


def test_sparse_model_with_the_same_config_loads(tmp_path):
    model = save_run(tmp_path, sparse=True)
    target = sparsify(TinyMDM(**KW), SparseConfig(reduction=0.7))
    loaded, config = load_checkpoint(str(tmp_path / "model000001.pt"), model=target)
    assert loaded is target and config == model._smdm_state.config
    for a, b in zip(model.state_dict().values(), loaded.state_dict().values()):
        assert torch.equal(a, b)
    # a field changed on purpose (e.g. sampling with another gamma) when named
    other = sparsify(TinyMDM(**KW), SparseConfig(reduction=0.7, gamma=0.3))
    load_checkpoint(str(tmp_path / "model000001.pt"), model=other, allow_differences=("gamma",))
    assert other._smdm_state.config.gamma == 0.3
    with pytest.raises(ValueError, match=r"allow_differences names unknown SparseConfig field\(s\) \['gama'\]"):
        load_checkpoint(str(tmp_path / "model000001.pt"), model=other, allow_differences=("gama",))


def test_args_json_config_disagreeing_is_named_too(tmp_path):
    model = save_run(tmp_path, sparse=True, with_config=False)
    (tmp_path / "args.json").write_text(json.dumps(model._smdm_state.config.to_args_dict()))
    with pytest.raises(ValueError, match=r"args.json\) in 1 field\(s\): reduction: saved 0.7, model 0.5"):
        load_checkpoint(str(tmp_path / "model000001.pt"), model=sparsify(TinyMDM(**KW), SparseConfig(reduction=0.5)))


def test_checkpoint_file_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such checkpoint file: .*missing.pt"):
        load_checkpoint(str(tmp_path / "missing.pt"))
    save_run(tmp_path, sparse=True, with_config=False)
    (tmp_path / "args.json").write_text('{"sparse": true, ')
    with pytest.raises(ValueError, match=r"args.json: not valid JSON"):
        load_checkpoint(str(tmp_path / "model000001.pt"))
    (tmp_path / "args.json").write_text(json.dumps({"sparse": True, "sparse_lipschitz": "no"}))
    with pytest.raises(TypeError, match=r"args.json: SparseConfig.lipschitz='no'"):
        find_sparse_config(str(tmp_path / "model000001.pt"))
    (tmp_path / "sparse_config.json").write_text('{"reduction": 0.7, "fsq": "on"}')
    with pytest.raises(TypeError, match=r"sparse_config.json: SparseConfig.fsq='on'"):
        load_checkpoint(str(tmp_path / "model000001.pt"))
