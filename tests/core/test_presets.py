"""The packaged presets: the paper's recipes (smdm_paper: App. B.1; sdip_paper: App. B.2), their
upstream sections checked against MDM's own argument parser, and the earlier presets kept."""
import importlib.util
import os
import re
from pathlib import Path

import pytest
import yaml

from smdm_plugin import SparseConfig, load_preset
from smdm_plugin.core.presets import preset_dirs

CONFIGS = Path(preset_dirs()[0])
PRESETS = sorted(p.stem for p in CONFIGS.glob("*.yaml"))
MDM_ROOT = os.environ.get("SMDM_MDM_ROOT")


def _yaml(name: str) -> dict:
    return yaml.safe_load((CONFIGS / f"{name}.yaml").read_text())


def test_smdm_paper_is_appendix_b1():
    c = load_preset("smdm_paper")
    assert c.enabled and c.diffusion_steps == 50
    assert c.fsq is True                                     # FSQ-quantised attention keys
    assert c.lipschitz is True and c.lipschitz_lambda == 0.0  # layers kept, L_lip excluded
    assert c.dynamic_update is False and c.dynamic is False   # Table 1 / Table 2 at 50 steps
    assert c.sample_interpolation == "linear"                 # the paper's fill (the default is auto)
    assert (c.reduction, c.selector, c.gamma, c.prefix_frames, c.interpolate) == (0.8, "vw", 0.1, 0, True)
    up = _yaml("smdm_paper")["upstream"]["mdm"]
    assert up["flags"] == {"arch": "trans_dec", "layers": 8, "latent_dim": 512, "diffusion_steps": 50}
    assert up["builtin"] == {"num_heads": 4, "dropout": 0.1, "ff_size": 1024}


def test_sdip_paper_is_appendix_b2():
    c = load_preset("sdip_paper")
    assert (c.diffusion_steps, c.prefix_frames, c.dynamic_update, c.dynamic) == (10, 20, False, False)
    assert c.fsq is True and c.lipschitz is True and c.lipschitz_lambda == 0.0
    flags = _yaml("sdip_paper")["upstream"]["mdm"]["flags"]
    assert (flags["context_len"], flags["pred_len"]) == (c.prefix_frames, 40)
    assert flags["text_encoder_type"] == "bert" and flags["arch"] == "trans_dec"


@pytest.mark.parametrize("name", PRESETS)
def test_every_preset_loads_and_agrees_with_its_upstream_section(name):
    c = load_preset(name)
    assert SparseConfig.from_dict(c.to_dict()) == c
    assert load_preset(str(CONFIGS / f"{name}.yaml")) == c   # by path, too
    flags = (_yaml(name).get("upstream") or {}).get("mdm", {}).get("flags", {})
    if "diffusion_steps" in flags:                            # one T for the model and the schedule
        assert flags["diffusion_steps"] == c.diffusion_steps
    if "context_len" in flags:
        assert flags["context_len"] == c.prefix_frames


def test_earlier_presets_are_named_variants_of_the_paper_recipe():
    """smdm_humanml / sdip stay loadable (checkpoints and scripts name them); they differ from the
    paper's recipes only in FSQ, λ and (smdm_humanml) the dynamic update."""
    paper, old = load_preset("smdm_paper").to_dict(), load_preset("smdm_humanml").to_dict()
    assert {k for k in paper if paper[k] != old[k]} == {"fsq", "lipschitz_lambda", "dynamic_update"}
    paper, old = load_preset("sdip_paper").to_dict(), load_preset("sdip").to_dict()
    assert {k for k in paper if paper[k] != old[k]} == {"fsq", "lipschitz_lambda"}


def _mdm_parser_util():
    spec = importlib.util.spec_from_file_location("mdm_parser_util", os.path.join(MDM_ROOT, "utils", "parser_util.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)  # stdlib only (argparse, os, json)
    return mod


def _argv(flags: dict) -> list:
    out = []
    for k, v in flags.items():
        out += [f"--{k}"] if v is True else [f"--{k}", str(v)]
    return out


@pytest.mark.skipif(not MDM_ROOT, reason="SMDM_MDM_ROOT not set (an MDM checkout)")
@pytest.mark.parametrize("name", [n for n in PRESETS if "mdm" in (_yaml(n).get("upstream") or {})])
def test_upstream_flags_parse_with_mdm(name):
    """Every flag is an option of MDM's train.train_mdm and parses to the preset's value; the
    'builtin' values are the ones MDM's get_model_args hard-codes."""
    pu = _mdm_parser_util()
    parser = pu.ArgumentParser()
    for add in (pu.add_base_options, pu.add_data_options, pu.add_model_options, pu.add_diffusion_options,
                pu.add_training_options):
        add(parser)
    up = _yaml(name)["upstream"]["mdm"]
    args = pu.apply_rules(parser.parse_args(_argv(up["flags"]) + ["--save_dir", "unused"]))
    for k, v in up["flags"].items():
        assert getattr(args, k) == v, k
    model_util = Path(MDM_ROOT, "utils", "model_util.py").read_text()
    for k, v in up.get("builtin", {}).items():
        assert re.search(rf"'{k}':\s*{re.escape(repr(v))}\b", model_util), k
    if "sample_flags" in up:
        gen = pu.ArgumentParser()
        for add in (pu.add_base_options, pu.add_sampling_options, pu.add_generate_options):
            add(gen)
        sargs = gen.parse_args(_argv(up["sample_flags"]) + ["--model_path", "unused"])
        assert all(getattr(sargs, k) == v for k, v in up["sample_flags"].items())


def test_presets_live_in_the_top_level_configs_folder_and_are_installed():
    """The presets are the project's top-level configs/ (a checkout, `pip install -e .`); setup.cfg
    installs every one of them as data files (<prefix>/share/smdm_plugin/configs), where
    preset_dirs() looks in a regular install."""
    import configparser
    from pathlib import Path

    from smdm_plugin.core.presets import preset_dirs

    from helpers.paths import ROOT as root
    assert Path(preset_dirs()[0]) == root / "configs"
    cfg = configparser.ConfigParser()
    cfg.read(root / "setup.cfg")
    installed = {k: v.split() for k, v in cfg["options.data_files"].items()}
    files = sorted(p.relative_to(root).as_posix() for p in (root / "configs").rglob("*.yaml"))
    covered = sorted(f for f in files for dest, globs in installed.items() for g in globs
                     if Path(f).match(g) and dest == "share/smdm_plugin/" + str(Path(f).parent))
    assert covered == files


def test_a_bare_name_is_always_the_packaged_preset(tmp_path, monkeypatch):
    """0.7.0 read ./zero_shot/ first when the current folder held one (reduction 0.5 instead of 0.8);
    a path (a separator, or a .json / .yaml ending) is a path."""
    from smdm_plugin.adapters.warm import _config

    monkeypatch.chdir(tmp_path)
    SparseConfig(reduction=0.5, selector="uniform").save(tmp_path / "zero_shot")  # zero_shot/sparse_config.json
    SparseConfig(reduction=0.6).save(tmp_path / "smdm_paper.yaml")
    packaged = load_preset(str(CONFIGS / "zero_shot.yaml"))
    assert load_preset("zero_shot") == packaged and packaged.reduction == 0.8
    assert _config("zero_shot", "wrap_dense") == packaged  # wrap_dense / --sparse_preset read it so
    assert load_preset(os.path.join(".", "zero_shot")).reduction == 0.5  # a path: the folder here
    assert load_preset("smdm_paper.yaml").reduction == 0.6 and load_preset("smdm_paper").reduction == 0.8
    assert load_preset(tmp_path / "zero_shot").reduction == 0.5  # a PathLike is a path
    (tmp_path / "mine").mkdir()
    SparseConfig(reduction=0.7).save(tmp_path / "mine")
    with pytest.raises(ValueError, match=r"unknown preset 'mine' .*; for the file or folder 'mine' here, pass ./mine"):
        load_preset("mine")
    with pytest.raises(FileNotFoundError, match="no such file: 'zero_shot.json'"):
        load_preset("zero_shot.json")
