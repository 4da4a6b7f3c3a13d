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


# ------------------------------------------------------------------------------ types, files, argparse
@pytest.mark.parametrize("field,value,needle", [
    ("lipschitz", "no", "expected a bool (true/false), got str"),
    ("enabled", 1, "expected a bool (true/false), got int"),
    ("dynamic_update", "false", "expected None or a bool (true/false), got str"),
    ("diffusion_steps", "50", "expected an integer >= 1, got str"),
    ("diffusion_steps", 50.0, "expected an integer >= 1, got float"),
    ("diffusion_steps", True, "expected an integer >= 1, got bool"),
    ("prefix_frames", 2.5, "got float"),
    ("lipschitz_hidden", 64.0, "expected None or an integer >= 1, got float"),
    ("fsq_levels", (8.7, 5), "got float element 8.7"),
    ("fsq_levels", (8, True), "got bool element True"),
    ("fsq_levels", "885", "got str"),
    ("reduction", "0.8", "got str"),
    ("reduction", True, "got bool"),
    ("selector", None, "got NoneType"),
    ("text_encoder", 5, "expected None or a non-empty string, got int"),
])
def test_wrong_types_are_type_errors(field, value, needle):
    from smdm_plugin.support.values import ConfigTypeError

    with pytest.raises(TypeError) as e:
        SparseConfig(**{field: value})
    assert isinstance(e.value, ConfigTypeError) and isinstance(e.value, ValueError)  # caught either way
    assert str(e.value).startswith(f"SparseConfig.{field}=") and needle in str(e.value)


@pytest.mark.parametrize("field,value", [
    ("gamma", float("inf")), ("gamma", float("nan")), ("lipschitz_lambda", float("inf")), ("reduction", float("nan")),
    ("sine_w0", float("inf")), ("frame_index_scale", 10 ** 400), ("fsq_levels", ()), ("text_encoder", "  "),
])
def test_non_finite_and_empty_values_are_rejected(field, value):
    with pytest.raises(ValueError, match=f"SparseConfig.{field}"):
        SparseConfig(**{field: value})


def test_values_are_normalised_and_replace_revalidates():
    import numpy as np

    c = SparseConfig(mask_noise=0, lipschitz_lambda=np.float32(0.5), diffusion_steps=np.int64(10), fsq_levels=[8, 5])
    assert type(c.mask_noise) is float and type(c.lipschitz_lambda) is float and type(c.diffusion_steps) is int
    assert c.fsq_levels == (8, 5) and c.text_encoder is None
    assert SparseConfig(text_encoder="dunzhang/stella_en_400M_v5").text_encoder == "dunzhang/stella_en_400M_v5"
    with pytest.raises(TypeError, match="SparseConfig.fsq"):
        c.replace(fsq="yes")
    assert c.replace(fsq=False).fsq is False and c.fsq is True


def test_unknown_keys_suggest_the_closest_name(tmp_path):
    with pytest.raises(ValueError, match=r"unknown option 'redution'; did you mean 'reduction'\?"):
        SparseConfig.from_dict({"reduction": 0.5, "redution": 0.4})
    with pytest.raises(ValueError, match=r"unknown option 'fsq_level'; did you mean 'fsq_levels'\?"):
        SparseConfig.from_yaml("fsq_level: [8, 5]\n")
    p = tmp_path / "c.yaml"
    p.write_text("lipschitz: false\nlipshitz_lambda: 0.1\n")
    with pytest.raises(ValueError, match=rf"^{p}: SparseConfig: unknown option 'lipshitz_lambda'; did you mean "
                                         r"'lipschitz_lambda'\?"):
        SparseConfig.load(p)


def test_file_errors_name_the_path(tmp_path):
    missing = tmp_path / "nope.json"
    for load in (SparseConfig.load, SparseConfig.from_json, SparseConfig.from_yaml):
        with pytest.raises(FileNotFoundError, match=f"no such config file: '{missing}'"):
            load(str(missing))
    with pytest.raises(FileNotFoundError, match="no such config file: 'nope'"):
        SparseConfig.from_json("nope")  # never parsed as JSON text
    with pytest.raises(FileNotFoundError, match="sparse_config.json"):
        SparseConfig.load(tmp_path)  # a folder without sparse_config.json
    with pytest.raises(ValueError, match="SparseConfig.from_json: not valid JSON"):
        SparseConfig.from_json("{")


@pytest.mark.parametrize("name,text,error,needle", [
    ("bad.json", '{"reduction": 0.7,', ValueError, "not valid JSON"),
    ("bad.yaml", "reduction: [0.7\n", ValueError, "not valid YAML"),
    ("bad.yaml", "reduction: 1.5\n", ValueError, "SparseConfig.reduction=1.5"),
    ("bad.yaml", "lipschitz: 'no'\n", TypeError, "SparseConfig.lipschitz='no'"),
    ("bad.yaml", "- 1\n- 2\n", TypeError, "expected a mapping"),
])
def test_bad_file_contents_name_the_file(tmp_path, name, text, error, needle):
    bad = tmp_path / name
    bad.write_text(text)
    with pytest.raises(error) as e:
        SparseConfig.load(bad)
    assert str(e.value).startswith(f"{bad}: ") and needle in str(e.value)


def test_sparse_section_is_the_config_and_other_sections_are_allowed(tmp_path):
    p = tmp_path / "preset.yaml"
    p.write_text("sparse:\n  reduction: 0.7\n  fsq: true\nupstream:\n  arch: trans_dec\n  diffusion_steps: 50\n")
    assert SparseConfig.load(p) == SparseConfig(reduction=0.7, fsq=True)
    # without a sparse section the whole mapping is the config: other sections are unknown keys
    p.write_text("reduction: 0.7\nupstream: {arch: trans_dec}\n")
    with pytest.raises(ValueError, match="unknown option 'upstream'"):
        SparseConfig.load(p)
    p.write_text("sparse: 0.7\n")
    with pytest.raises(TypeError, match="the 'sparse' section must be a mapping"):
        SparseConfig.load(p)
    j = tmp_path / "c.json"
    j.write_text(json.dumps({"sparse": {"selector": "uniform"}, "notes": "anything"}))
    assert SparseConfig.load(j).selector == "uniform"
    assert SparseConfig.from_yaml("") == SparseConfig()  # an empty file: the defaults


def test_save_and_to_json_write_atomically(tmp_path, monkeypatch):
    import smdm_plugin.support.atomic as atomic

    p = tmp_path / "sparse_config.json"
    SparseConfig(reduction=0.6).save(tmp_path)
    before = p.read_bytes()

    def crash(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(atomic.os, "fsync", crash)  # the write fails before the rename
    with pytest.raises(OSError, match="disk full"):
        SparseConfig(reduction=0.7).save(tmp_path)
    with pytest.raises(OSError, match="disk full"):
        SparseConfig(reduction=0.7).to_yaml(tmp_path / "c.yaml")
    assert p.read_bytes() == before and sorted(f.name for f in tmp_path.iterdir()) == ["sparse_config.json"]
    monkeypatch.undo()
    SparseConfig(reduction=0.7).to_yaml(tmp_path / "c.yaml")
    assert SparseConfig.load(tmp_path / "c.yaml").reduction == 0.7


def _parser():
    p = argparse.ArgumentParser(prog="train")
    SparseConfig.add_argparse_args(p)
    return p


@pytest.mark.parametrize("field,value,needle", [
    ("reduction", "1.0", "must be a finite number in [0, 1), got 1.0"),
    ("reduction", "nan", "must be a finite number in [0, 1)"),
    ("gamma", "-0.1", "must be a finite number in [0, 1]"),
    ("mask_noise", "x", "expected a number, got 'x'"),
    ("diffusion_steps", "0", "must be an integer >= 1, got 0"),
    ("diffusion_steps", "8.7", "expected an integer, got '8.7'"),
    ("prefix_frames", "-1", "must be an integer >= 0"),
    ("sine_w0", "0", "must be a finite number > 0"),
    ("lipschitz_layers", "0", "must be an integer >= 1"),
    ("lipschitz_hidden", "0", "must be an integer >= 1"),
    ("lipschitz_lambda", "inf", "must be a finite number >= 0"),
    ("frame_index_scale", "-1", "must be a finite number >= 0"),
    ("fsq_levels", "8 1", "must be an integer >= 2, got 1"),
    ("lipschitz", "maybe", "expected a boolean (true/false), got 'maybe'"),
    ("text_encoder", "", "expected a non-empty string"),
    ("selector", "VW", "invalid choice: 'VW'"),
])
def test_argparse_options_are_range_checked(field, value, needle, capsys):
    with pytest.raises(SystemExit) as e:
        _parser().parse_args([f"--sparse_{field}", *value.split(" ")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and f"argument --sparse_{field}: {needle}" in err and "Traceback" not in err


def test_every_field_declares_its_spec_and_default():
    import dataclasses

    from smdm_plugin.core.config import FieldSpec, spec_of

    for f in dataclasses.fields(SparseConfig):
        assert isinstance(spec_of(f), FieldSpec) and spec_of(f).help
        # the default passes its own check
        assert getattr(SparseConfig(), f.name) == (f.default if f.name != "fsq_levels" else tuple(f.default))


def test_argparse_every_field_and_none_for_optional_ones():
    p = _parser()
    flags = {a.dest for a in p._actions}
    fields = set(SparseConfig().to_dict()) - {"enabled", "version"}
    assert {f"sparse_{f}" for f in fields} <= flags
    a = p.parse_args(["--sparse", "--sparse_lipschitz_hidden", "64", "--sparse_dynamic_update", "auto",
                      "--sparse_text_encoder", "stella", "--sparse_fsq", "yes"])
    c = SparseConfig.from_args(a)
    assert (c.lipschitz_hidden, c.dynamic_update, c.text_encoder, c.fsq) == (64, None, "stella", True)
    assert SparseConfig.from_args(p.parse_args(["--sparse_lipschitz_hidden", "none"])).lipschitz_hidden is None
    assert SparseConfig.from_args(c.to_args_dict()) == c
    # what MDM's args.json holds is checked like anything else
    with pytest.raises(TypeError, match="SparseConfig.lipschitz='no'"):
        SparseConfig.from_args({"sparse": True, "sparse_lipschitz": "no"})


def test_preset_errors():
    with pytest.raises(ValueError, match=r"unknown preset 'smdm_humanl'; did you mean 'smdm_humanml'\?"):
        load_preset("smdm_humanl")
    with pytest.raises(FileNotFoundError, match="no such file: 'configs/x.yaml'"):
        load_preset("configs/x.yaml")


# ----------------------------------------------------------------------------------------- messages
def test_sparse_config_unknown_keyword_names_the_closest_field():
    from smdm_plugin import SparseConfig

    with pytest.raises(TypeError, match="'redution'.*did you mean 'reduction'"):
        SparseConfig(redution=0.8)
    assert SparseConfig(reduction=0.5).reduction == 0.5
