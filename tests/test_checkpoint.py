import json

import pytest
import torch

from smdm_plugin import SparseConfig, TinyMDM, check_state_dict, load_checkpoint, save_sparse_config, sparsify
from smdm_plugin.io.checkpoint import find_sparse_config

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
    assert config == model.smdm_config and loaded.smdm_config.reduction == 0.7
    x, t = torch.randn(2, 263, 1, 30), torch.tensor([1, 2])
    y = {"text_embed": torch.randn(1, 2, 512)}
    with torch.no_grad():
        assert torch.equal(loaded.eval()(x, t, y), model.eval()(x, t, y))


def test_mdm_args_json_is_enough(tmp_path):
    model = save_run(tmp_path, sparse=True, with_config=False)
    (tmp_path / "args.json").write_text(json.dumps({"arch": "trans_enc", **model.smdm_config.to_args_dict()}))
    assert find_sparse_config(str(tmp_path / "model000001.pt")) == model.smdm_config
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
    cfg = SparseConfig()
    save_sparse_config(cfg, str(tmp_path))
    with pytest.raises(FileExistsError):
        save_sparse_config(cfg, str(tmp_path), overwrite=False)
    with pytest.raises(ValueError, match="not sparse"):
        save_sparse_config(TinyMDM(**KW), str(tmp_path))
