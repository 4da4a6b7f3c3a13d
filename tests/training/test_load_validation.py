"""A trained model folder is validated as it is loaded (``load_trained`` / ``load_bundle``): an empty or
truncated checkpoint, files that are not UTF-8, missing fields, ranges, statistics, non-finite weights, and
options files (``args.json``, MotionDiffuse's ``opt.txt``) that disagree with ``sparse_config.json`` are
one line naming the file, never a silent wrong result."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from smdm_plugin.core.config import SparseConfig
from smdm_plugin.training import trainer as T

from helpers.commands import train as _train


@pytest.fixture
def data(synthetic_hml) -> Path:
    return synthetic_hml


# ------------------------------------------------------------------------------ loads validate
@pytest.fixture
def model_dir(tmp_path, data) -> Path:
    out = tmp_path / "m"
    assert _train(data, out, "--sparse", "--steps", "1") == 0
    return out


@pytest.mark.parametrize("edit,match", [
    (lambda d: (d / "model000000001.pt").write_bytes(b""), r"model000000001.pt: empty checkpoint file"),
    (lambda d: (d / "model000000001.pt").write_bytes((d / "model000000001.pt").read_bytes()[:300]),
     r"model000000001.pt: not a readable checkpoint \(truncated or corrupt"),
    (lambda d: (d / "args.json").write_bytes(b'{"sparse": true, "sparse_reduction": "\xff"}'),
     r"args.json: not UTF-8 text"),
    (lambda d: (d / "sparse_config.json").write_bytes(b"\xff\xfe{}"), r"sparse_config.json: not UTF-8"),
    (lambda d: (d / "sparse_config.json").write_text('{"reduction": 0.8}'),
     r"sparse_config.json: missing field\(s\) enabled, selector"),
    (lambda d: (d / "args.json").write_text('{"sparse": true, "sparse_reduction": 0.5}'),
     r"args.json and .*sparse_config.json disagree: reduction: args.json 0.5, sparse_config.json 0.8"),
    (lambda d: _edit_json(d / "train_config.json", diffusion_steps=0), r"train_config.json: diffusion_steps=0: expected an integer >= 1"),
    (lambda d: _edit_json(d / "train_config.json", diffusion_steps=-5), r"diffusion_steps=-5"),
    (lambda d: _edit_json(d / "train_config.json", steps="many"), r"train_config.json: steps='many'"),
    (lambda d: np.save(d / "Std.npy", np.r_[np.nan, np.ones(262)].astype(np.float32)), r"Std.npy: std holds a non-finite"),
    (lambda d: np.save(d / "Std.npy", np.ones(10, np.float32)), r"Std.npy: std must have shape \[263\], got \[10\]"),
    (lambda d: np.save(d / "Std.npy", np.zeros(263, np.float32)), r"Std.npy: std must be > 0 everywhere"),
    (lambda d: np.save(d / "Mean.npy", np.ones(263, np.complex64)), r"Mean.npy: mean must be real numbers"),
    (lambda d: _edit_json(d / "backbone.json", njoints=0), r"backbone.json: njoints=0"),
])
def test_loads_validate_what_they_read(model_dir, edit, match):
    edit(model_dir)
    with pytest.raises(ValueError, match=match) as e:
        T.load_trained(str(model_dir))
    assert "\n" not in str(e.value)


def test_nonfinite_weights_are_refused(model_dir):
    sd = torch.load(model_dir / "model000000001.pt", weights_only=True)
    k = next(k for k, v in sd.items() if v.is_floating_point())
    sd[k] = sd[k].clone().fill_(float("nan"))
    torch.save(sd, model_dir / "model000000001.pt")
    with pytest.raises(ValueError, match=rf"tensor {k} holds non-finite values"):
        T.load_trained(str(model_dir))


def _edit_json(path: Path, **changes) -> None:
    path.write_text(json.dumps({**json.loads(path.read_text()), **changes}))


def test_bundle_motion_json_is_validated(tmp_path):
    from smdm_plugin.training.bundle import load_bundle, save_bundle
    from smdm_plugin.io.representation import Representation
    from smdm_plugin.reference.backbone import TinyMDM
    from smdm_plugin.reference.simple_diffusion import SimpleDiffusion

    rep = Representation("joints66")
    kw = dict(njoints=66, nfeats=1, latent_dim=16, ff_size=32, num_layers=1, num_heads=2, cond_mode="no_cond")
    d = save_bundle(str(tmp_path / "b"), TinyMDM(**kw), SimpleDiffusion(10), kw, rep, np.zeros(66), np.ones(66))
    load_bundle(d)
    for change, match in ((dict(fps=0), r"motion.json: fps=0: expected a finite number > 0"),
                          (dict(diffusion_steps=0), r"diffusion_steps=0: expected an integer >= 1"),
                          (dict(std=[1.0] * 65), r"std must have shape \[66\]"),
                          (dict(mean=[float("nan")] + [0.0] * 65), r"mean holds a non-finite")):
        text = (tmp_path / "b" / "motion.json").read_text()
        _edit_json(tmp_path / "b" / "motion.json", **change)
        with pytest.raises(ValueError, match=match):
            load_bundle(d)
        (tmp_path / "b" / "motion.json").write_text(text)
    meta = json.loads((tmp_path / "b" / "motion.json").read_text())
    del meta["fps"]
    (tmp_path / "b" / "motion.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match=r"motion.json: missing field\(s\) fps"):
        load_bundle(d)


def test_options_files_must_agree_with_the_saved_config(model_dir, tmp_path):
    import argparse

    from smdm_plugin.families.motiondiffuse.upstream import config_from_opt

    # diffusion_steps is set from the diffusion when the model is built: a CLI default there is fine
    (model_dir / "args.json").write_text('{"sparse": true, "sparse_diffusion_steps": 50, "sparse_reduction": 0.8}')
    T.load_trained(str(model_dir))
    # MotionDiffuse: opt.txt's sparse_* options (strings, as get_opt reads them) vs sparse_config.json
    (tmp_path / "model").mkdir()
    SparseConfig(reduction=0.7).save(tmp_path / "model")
    opt = argparse.Namespace(is_train=False, model_dir=str(tmp_path / "model"), sparse="True", sparse_reduction="0.7",
                             sparse_diffusion_steps="50")
    assert config_from_opt(opt).reduction == 0.7
    opt.sparse_reduction = "0.5"
    with pytest.raises(ValueError, match=r"opt.txt and .*sparse_config.json disagree: reduction: opt.txt 0.5, "
                                         r"sparse_config.json 0.7"):
        config_from_opt(opt)


# ------------------------------------------------------------------------------ the files of a run agree
def _loaders():
    from smdm_plugin.adapters.checkpoint import load_checkpoint
    from smdm_plugin.training.bundle import load_bundle

    return {"load_trained": lambda d: T.load_trained(str(d)), "load_bundle": lambda d: load_bundle(str(d)),
            "load_checkpoint": lambda d: load_checkpoint(str(next(d.glob("model*.pt"))))}


@pytest.mark.parametrize("loader", ["load_trained", "load_bundle", "load_checkpoint"])
@pytest.mark.parametrize("edit,match", [
    # 0.7.0 loaded this as 50% dropped, uniform: only diffusion_steps was compared
    (lambda d: _edit_json(d / "sparse_config.json", reduction=0.5, selector="uniform"),
     r"train_config.json and .*sparse_config.json disagree: reduction: train_config.json 0.8, sparse_config.json 0.5; "
     r"selector: train_config.json 'vw', sparse_config.json 'uniform'"),
    (lambda d: _edit_json(d / "train_config.json", sparse=None), r"train_config.json says the run was dense, but "
                                                                 r".*sparse_config.json holds a sparse config"),
    (lambda d: _edit_json(d / "backbone.json", dropout=0.0),
     r"train_config.json and .*backbone.json disagree: dropout: train_config.json 0.1, backbone.json 0.0"),
    (lambda d: _edit_json(d / "motion.json", diffusion_steps=50),
     r"sparse_config.json and .*motion.json disagree: diffusion_steps: sparse_config.json 10, motion.json 50"),
    (lambda d: _edit_json(d / "sparse_config.json", diffusion_steps=50),
     r"sparse_config.json and .*motion.json disagree: diffusion_steps: sparse_config.json 50, motion.json 10"),
])
def test_the_files_of_a_run_must_agree(model_dir, loader, edit, match):
    """Every field two files of one run both hold agrees, or the load is one line naming both files and
    the fields (the fields the adapter sets from the model aside: train_config.json's sparse
    diffusion_steps is the command line's default, the model's is --diffusion-steps)."""
    _loaders()[loader](model_dir)
    edit(model_dir)
    with pytest.raises(ValueError, match=match) as e:
        _loaders()[loader](model_dir)
    assert "\n" not in str(e.value)


@pytest.fixture
def text_model(tmp_path) -> Path:
    from helpers.synthetic_data import write_humanml3d

    data = write_humanml3d(tmp_path / "captioned", captions=True)
    out = tmp_path / "t"
    assert _train(data, out, "--text", "--steps", "1") == 0
    return out


def test_a_text_model_without_its_text_encoder_is_refused(text_model):
    """0.7.0 sampled it unconditionally and called it "unconditional (trained without text)"."""
    (text_model / "train_config.json").rename(text_model / "kept.json")  # without it too: backbone.json says text
    (text_model / "text_encoder.json").unlink()
    for load in _loaders().values():
        with pytest.raises(ValueError, match=r"text_encoder.json: missing, but .*backbone.json says cond_mode 'text'"):
            load(text_model)


def test_a_text_encoder_config_must_agree_with_the_run(text_model):
    _edit_json(text_model / "text_encoder.json", guidance_scale=1.0)
    with pytest.raises(ValueError, match=r"train_config.json and .*text_encoder.json disagree: guidance_scale: "
                                         r"train_config.json 2.5, text_encoder.json 1.0"):
        T.load_trained(str(text_model))
