"""What the library refuses when it loads or converts a model: a config changed after it was built,
statistics of the wrong shape, arguments of the wrong type, checkpoint files that disagree with each
other or with the weights (each a ValueError / TypeError naming what is wrong, never a silent load),
and the statistics ``load_checkpoint`` is handed reaching an already-sparse model."""
import json

import numpy as np
import pytest
import torch

from smdm_plugin import (SparseConfig, TinyMDM, is_sparse, load_checkpoint, save_sparse_config, sparsify,
                         unsparsify)
from smdm_plugin.adapters.state import get_state
from smdm_plugin.io.checkpoint_files import CheckpointMismatchError

KW = dict(latent_dim=32, ff_size=64, num_layers=1)


def sparse_run(tmp_path, config=None, **kw):
    """A sparse checkpoint folder: weights, sparse_config.json, backbone.json."""
    torch.manual_seed(0)
    model = sparsify(TinyMDM(**KW), config or SparseConfig(reduction=0.5), **kw)
    save_sparse_config(model, str(tmp_path))
    torch.save(model.state_dict(), tmp_path / "model.pt")
    (tmp_path / "backbone.json").write_text(json.dumps(KW))
    return model, str(tmp_path / "model.pt")


def edit_json(path, **changes):
    d = json.loads(path.read_text())
    d.update(changes)
    path.write_text(json.dumps(d))


def edit_weights(path, key, value):
    sd = torch.load(path)
    sd[key] = value(sd[key]) if callable(value) else value
    torch.save(sd, path)


def test_sparsify_checks_a_config_changed_after_it_was_built_and_leaves_it_alone():
    c = SparseConfig()
    c.reduction = 5.0
    with pytest.raises(ValueError, match="reduction=5.0"):
        sparsify(TinyMDM(**KW), c)
    c = SparseConfig(reduction=0.5)
    c.fsq_levels = [5, 5, 5]                       # a list where the field holds a tuple: normalised in the copy
    m = sparsify(TinyMDM(**KW), c)
    assert get_state(m).config.fsq_levels == (5, 5, 5) and c.fsq_levels == [5, 5, 5]


@pytest.mark.parametrize("mean,std,needle", [
    (np.zeros(3), np.ones(4), "mean and std must both be [D], got 3 and 4 values"),
    (np.zeros((263, 2)), None, "mean must be [D] (one value per motion feature), got shape (263, 2)"),
    (None, np.float32(1.0), "std must be [D] (one value per motion feature), got shape ()"),
])
def test_statistics_must_be_one_value_per_feature(mean, std, needle):
    with pytest.raises(ValueError, match=needle.replace("[", r"\[").replace("(", r"\(").replace(")", r"\)")):
        sparsify(TinyMDM(**KW), mean=mean, std=std)


@pytest.mark.parametrize("call,needle", [
    (lambda: sparsify(TinyMDM(**KW), family=5), "sparsify: family must be a family name or a ModelFamily"),
    (lambda: sparsify(5), "sparsify: model must be a torch.nn.Module, got int"),
    (lambda: unsparsify(None), "unsparsify: model must be a torch.nn.Module, got NoneType"),
    (lambda: is_sparse(5), "is_sparse: model must be a torch.nn.Module"),
    (lambda: load_checkpoint(None), "load_checkpoint: path must be a file path, got NoneType"),
    (lambda: SparseConfig.from_args(None), "from_args: expected an argparse namespace or a mapping"),
])
def test_arguments_of_the_wrong_type_are_named(call, needle):
    with pytest.raises(TypeError, match=needle):
        call()


def test_load_checkpoint_checks_its_arguments(tmp_path):
    _, path = sparse_run(tmp_path)
    with pytest.raises(TypeError, match="model must be a torch.nn.Module or None, got int"):
        load_checkpoint(path, model=5)
    with pytest.raises(TypeError, match="got an unexpected keyword argument 'mena'"):
        load_checkpoint(path, mena=np.zeros(263))
    # a bare string would be read letter by letter; checked for a dense model too
    with pytest.raises(TypeError, match=r"allow_differences must be a sequence of field names, got the string 'gamma'"):
        load_checkpoint(path, allow_differences="gamma")
    with pytest.raises(ValueError, match="unknown SparseConfig field"):
        load_checkpoint(path, model=TinyMDM(**KW), allow_differences=("gama",))


def test_statistics_reach_an_already_sparse_model(tmp_path):
    mean, std = torch.randn(263), torch.rand(263) + 0.5
    _, path = sparse_run(tmp_path)
    target = sparsify(TinyMDM(**KW), SparseConfig(reduction=0.5))
    assert get_state(target).schedule.mean is None
    loaded, _ = load_checkpoint(path, model=target, mean=mean, std=std)
    assert torch.equal(get_state(loaded).schedule.mean, mean) and torch.equal(get_state(loaded).schedule.std, std)
    with pytest.raises(ValueError, match="already sparse: call attach_diffusion"):
        load_checkpoint(path, model=sparsify(TinyMDM(**KW), SparseConfig(reduction=0.5)), diffusion=object())


def test_args_json_saying_dense_beside_a_sparse_config_is_an_error(tmp_path):
    _, path = sparse_run(tmp_path)
    (tmp_path / "args.json").write_text(json.dumps({"sparse": False, "arch": "trans_enc"}))
    with pytest.raises(ValueError, match="args.json says the run was dense"):
        load_checkpoint(path)


def test_a_misspelt_sparse_option_is_an_error_not_a_default(tmp_path):
    with pytest.raises(ValueError, match="unknown option 'sparse_redution'; did you mean 'sparse_reduction'"):
        SparseConfig.from_args({"sparse": True, "sparse_redution": 0.5})
    with pytest.raises(ValueError, match="sparse must be true or false, got 0"):
        SparseConfig.from_args({"sparse": 0})
    # the integrations' own run options share the prefix and are no field
    assert SparseConfig.from_args({"sparse": True, "sparse_compile": "none", "lr": 1e-4}).enabled
    model, path = sparse_run(tmp_path)
    (tmp_path / "args.json").write_text(json.dumps({**model._smdm_state.config.to_args_dict(), "sparse_gamme": 0.3}))
    with pytest.raises(ValueError, match="args.json: SparseConfig: unknown option 'sparse_gamme'"):
        load_checkpoint(path)


def test_top_level_options_beside_a_sparse_section_are_an_error():
    with pytest.raises(ValueError, match="option\\(s\\) 'reduction', 'gamma' at the top level beside the 'sparse'"):
        SparseConfig.from_json('{"sparse": {"reduction": 0.5}, "reduction": 0.7, "gamma": 0.3}')
    # other sections (a preset's upstream: settings) stay allowed
    assert SparseConfig.from_json('{"sparse": {"reduction": 0.5}, "upstream": {"lr": 1}}').reduction == 0.5


def test_weights_that_disagree_with_the_config_name_the_files(tmp_path):
    _, path = sparse_run(tmp_path, SparseConfig(reduction=0.5, fsq_levels=(5, 5, 5)))
    edit_json(tmp_path / "sparse_config.json", fsq_levels=[8, 8])
    with pytest.raises(ValueError, match=r"key_down.weight has shape \(3, 8\), the model's \(2, 8\) .*sparse_config"):
        load_checkpoint(path)


@pytest.mark.parametrize("value,needle", [
    (lambda w: torch.ones_like(w, dtype=torch.bool), "is torch.bool, expected a floating tensor"),
    (lambda w: torch.ones_like(w, dtype=torch.int64), "is torch.int64, expected a floating tensor"),
])
def test_weights_of_another_kind_are_refused(tmp_path, value, needle):
    _, path = sparse_run(tmp_path)
    edit_weights(path, "seqTransEncoder.layers.0.linear1.weight", value)
    with pytest.raises(ValueError, match=needle):
        load_checkpoint(path)


def test_the_sparse_marker_must_hold_the_config_version(tmp_path):
    _, path = sparse_run(tmp_path)
    edit_weights(path, "smdm_sparse_version", torch.tensor(99))
    with pytest.raises(ValueError, match="smdm_sparse_version is 99, but the config it is loaded with has version 1"):
        load_checkpoint(path)


def test_mismatch_errors_are_value_errors_and_still_runtime_errors(tmp_path):
    torch.save(TinyMDM(**KW).state_dict(), tmp_path / "dense.pt")
    with pytest.raises(CheckpointMismatchError) as e:
        load_checkpoint(str(tmp_path / "dense.pt"), model=sparsify(TinyMDM(**KW)))
    assert isinstance(e.value, ValueError) and isinstance(e.value, RuntimeError)


@pytest.mark.parametrize("call,error,needle", [
    (lambda: SparseConfig.from_json("[1]"), ValueError, "expected a mapping of SparseConfig options, got list"),
    (lambda: SparseConfig.from_yaml("reduction: 1e-1"), ValueError, "YAML reads 1e-1 as a string"),
    (lambda: SparseConfig().sample_fill(263.7), TypeError, "D must be a positive int"),
    (lambda: SparseConfig().feature_kind("abc"), TypeError, "D must be a positive int"),
    (lambda: SparseConfig().differences(5), TypeError, "differences: expected a SparseConfig, got int"),
])
def test_config_methods_name_what_they_expected(call, error, needle):
    with pytest.raises(error, match=needle):
        call()
