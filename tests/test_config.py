import argparse
import json

import pytest

from smdm_plugin import SparseConfig, load_preset


@pytest.mark.parametrize("field,value,needle", [
    ("reduction", 1.0, "[0, 1)"), ("reduction", -0.1, "[0, 1)"), ("selector", "foo", "vw"),
    ("feature", "smpl", "humanml3d"), ("gamma", 1.5, "[0, 1]"), ("mask_noise", 2.0, "[0, 1]"),
    ("diffusion_steps", 0, ">= 1"), ("lipschitz_layers", 0, ">= 1"), ("sine_w0", 0.0, "> 0"),
    ("fsq_levels", (8, 1), ">= 2"), ("attention_backend", "xformers", "compact"),
    ("lipschitz_lambda", -1.0, ">= 0"), ("frame_index_scale", -1.0, ">= 0"), ("version", 99, "newer"),
])
def test_validation_names_field_and_range(field, value, needle):
    with pytest.raises(ValueError) as e:
        SparseConfig(**{field: value})
    assert f"SparseConfig.{field}" in str(e.value) and needle in str(e.value)


def test_json_yaml_roundtrip(tmp_path):
    c = SparseConfig(reduction=0.7, selector="mdo", fsq=True, fsq_levels=(7, 5, 5), lipschitz_hidden=128)
    assert SparseConfig.from_json(c.to_json()) == c
    assert SparseConfig.from_yaml(c.to_yaml()) == c
    p = c.save(str(tmp_path))
    assert p.endswith("sparse_config.json") and SparseConfig.load(str(tmp_path)) == c
    assert json.load(open(p))["version"] == 1
    with pytest.raises(ValueError, match="unknown option"):
        SparseConfig.from_dict({"reduction": 0.5, "redution": 0.4})


def test_argparse_prefix_roundtrip():
    parser = argparse.ArgumentParser()
    parser.add_argument("--batch_size", type=int, default=64)
    SparseConfig.add_argparse_args(parser)
    args = parser.parse_args(["--sparse", "--sparse_reduction", "0.9", "--sparse_selector", "uniform",
                              "--sparse_gamma", "0.2", "--sparse_dynamic_update", "false",
                              "--sparse_fsq_levels", "8", "6"])
    c = SparseConfig.from_args(args)
    assert (c.enabled, c.reduction, c.selector, c.gamma, c.dynamic_update, c.fsq_levels) == \
        (True, 0.9, "uniform", 0.2, False, (8, 6))
    assert SparseConfig.from_args(parser.parse_args([])).enabled is False
    assert SparseConfig.from_args(c.to_args_dict()) == c  # what args.json stores
    with pytest.raises(SystemExit):
        parser.parse_args(["--sparse_selector", "nope"])


def test_presets():
    s = load_preset("smdm_humanml")
    assert (s.reduction, s.diffusion_steps, s.selector) == (0.8, 50, "vw")
    d = load_preset("sdip")
    assert d.prefix_frames == 20 and d.dynamic_update is False
    assert load_preset("smotiondiffuse").enabled
    with pytest.raises(ValueError, match="unknown preset"):
        load_preset("nope")
