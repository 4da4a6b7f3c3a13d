"""Every file a sparse upstream run writes states the settings that ran (issue 21): DiP's
``args.json`` vs ``sparse_config.json`` (prefix, diffusion steps), priorMDM training and DoubleTake
sampling write ``sparse_config.json``, MotionDiffuse's ``opt.txt`` says ``sparse_fsq False`` when
FSQ keys could not apply (with a warning); DoubleTake's fixed 196-frame ``y['mask']`` gives no
mask-length warning. Upstream's writes are imitated as upstream does them (``json.dump(vars(args),
indent=4, sort_keys=True)``; MotionDiffuse's ``key: value`` lines)."""
import argparse
import json
import os
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest
import torch

from smdm_plugin import SparseConfig, TinyMDM
from smdm_plugin.core.agreement import disagreement
from smdm_plugin.support.config_files import CONFIG_FILENAME
from smdm_plugin.families.mdm.upstream import add_sparse_options, sample_output_dir, sparsify_mdm
from smdm_plugin.families.doubletake.upstream import doubletake_output_dir, sparsify_priormdm
from smdm_plugin.reference.simple_diffusion import SimpleDiffusion

from smdm_plugin.families.motiondiffuse.standin import StandInDiffusion, StandInMotionTransformer
from helpers.paths import ROOT


def _train_args(save_dir: str, *argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_sparse_options(parser)
    args = parser.parse_args(["--sparse", "--sparse_feature", "raw", *argv])
    args.save_dir, args.overwrite = save_dir, False
    return args


def _upstream_args_json(args: argparse.Namespace) -> str:
    os.makedirs(args.save_dir, exist_ok=True)
    path = os.path.join(args.save_dir, "args.json")
    with open(path, "w") as fw:  # what MDM's train_mdm.py writes before building the model
        json.dump(vars(args), fw, indent=4, sort_keys=True)
    return path


def _agree(save_dir: str, options: dict, options_file: str) -> None:
    saved = SparseConfig.load(os.path.join(save_dir, CONFIG_FILENAME))
    assert disagreement(saved, options, "sparse_config.json", options_file, ignore=("version",)) is None


class doubleTake_TinyMDM(TinyMDM):  # noqa: N801 - named like priorMDM's doubleTake_MDM
    pass


def _quiet(fn, *a):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*a)


def test_dip_args_json_states_the_prefix_and_steps_that_ran(tmp_path):
    args = _train_args(str(tmp_path / "run"))
    path = _upstream_args_json(args)
    before = json.load(open(path))
    assert before["sparse_prefix_frames"] == 0 and before["sparse_diffusion_steps"] == 50
    model = TinyMDM(njoints=8, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, cond_mode="no_cond",
                    context_len=20, pred_len=40)
    _quiet(sparsify_mdm, model, args, None, SimpleDiffusion(10))
    after = json.load(open(path))
    assert after["sparse_prefix_frames"] == 20 and after["sparse_diffusion_steps"] == 10
    assert args.sparse_prefix_frames == 20 and args.sparse_diffusion_steps == 10
    _agree(args.save_dir, after, path)
    # the other entries are upstream's, untouched
    assert {k: v for k, v in after.items() if not k.startswith("sparse")} == \
        {k: v for k, v in before.items() if not k.startswith("sparse")}


def test_priormdm_training_writes_sparse_config_and_agreeing_args_json(tmp_path):
    args = _train_args(str(tmp_path / "run"), "--sparse_reduction", "0.7")
    path = _upstream_args_json(args)
    model = TinyMDM(njoints=8, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, cond_mode="no_cond")
    _quiet(sparsify_priormdm, model, args, None, SimpleDiffusion(20))
    assert os.path.isfile(os.path.join(args.save_dir, CONFIG_FILENAME))
    after = json.load(open(path))
    assert after["sparse_diffusion_steps"] == 20 and after["sparse_reduction"] == 0.7
    _agree(args.save_dir, after, path)


def _dt_args(**kw):
    base = dict(model_path="save/my_model/model000200000.pt", output_dir="", input_text="", sample_gt=False,
                double_take=True, seed=10, handshake_size=20, blend_len=5, skip_steps_double_take=100)
    return argparse.Namespace(**{**base, **kw})


@pytest.mark.parametrize("kw,name", [
    ({}, "DoubleTake_samples_my_model_000200000_seed10_handshake_20_double_take_blend_5_skipSteps_100"),
    ({"seed": 3, "handshake_size": 10, "blend_len": 20, "skip_steps_double_take": 0},
     "DoubleTake_samples_my_model_000200000_seed3_handshake_10_double_take_blend_20_skipSteps_0"),
    ({"input_text": "texts/my prompts.v2.txt"},
     "DoubleTake_samples_my_model_000200000_seed10_my_promptsv2_handshake_20_double_take_blend_5_skipSteps_100"),
    ({"input_text": "a/b.csv", "sample_gt": True},
     "DoubleTake_samples_my_model_000200000_seed10_b_gt_handshake_20_double_take_blend_5_skipSteps_100"),
])
def test_doubletake_output_dir_is_derived_from_the_args_as_upstream_does(kw, name):
    """Expected names written out by hand from priorMDM's sample/double_take.py."""
    assert doubletake_output_dir(_dt_args(**kw)) == os.path.abspath(os.path.join("save", "my_model", name))


def test_doubletake_output_dir_given_or_impossible():
    assert doubletake_output_dir(_dt_args(output_dir="res/x")) == os.path.abspath("res/x")
    assert doubletake_output_dir(_dt_args(input_text="prompts.json")) is None   # upstream raises TypeError
    assert doubletake_output_dir(_dt_args(model_path=None)) is None


def _sampling_run(cwd, args: str, then: str, model: str = "doubleTake_TinyMDM", entry: str = "priormdm",
                  sparse: bool = True, extra: str = "") -> subprocess.CompletedProcess:
    """A sampling run in a child process, in ``cwd`` (sparse_config.json is written when the process
    ends, after upstream has replaced its output folder): build ``model`` (``doubleTake_TinyMDM``,
    ``TinyMDM``, ``DiP``), call the integration's entry point (``priormdm``: ``sparsify_priormdm``,
    ``mdm``: ``sparsify_mdm``) with the option values ``args`` (Python keyword text), then run
    ``then`` (writes the outputs as upstream does). ``extra``: code run first (upstream's set-up)."""
    script = textwrap.dedent("""
        import argparse, os, time, warnings, numpy as np
        {extra}
        from smdm_plugin import TinyMDM
        from smdm_plugin.families.doubletake.upstream import sparsify_priormdm
        from smdm_plugin.families.mdm.upstream import sparsify_mdm
        class doubleTake_TinyMDM(TinyMDM):
            pass
        kw = dict(njoints=8, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, cond_mode="no_cond")
        m = {model}(**kw) if {model!r} != "DiP" else TinyMDM(context_len=20, pred_len=40, **kw)
        settings = dict(sparse_feature="raw", sparse_reduction=0.75) if {sparse} else {{}}  # (dense: none, or refused)
        args = argparse.Namespace(sparse={sparse}, blend_len=5, {args}, **settings)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")   # (no dataset Mean/Std here)
            sparsify_{entry}(m, args)
    """).format(args=args, model=model, entry=entry, sparse=sparse, extra=extra) + textwrap.dedent(then)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run([sys.executable, "-c", script], env=env, cwd=str(cwd), timeout=300,
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return proc


def test_doubletake_sampling_writes_sparse_config_beside_its_outputs(tmp_path):
    """With --output_dir: that folder's sparse_config.json is the model's config."""
    out = tmp_path / "out"
    _sampling_run(tmp_path, f"model_path={str(tmp_path / 'model000001.pt')!r}, output_dir={str(out)!r}", """
        os.makedirs(args.output_dir)
        np.save(os.path.join(args.output_dir, "results.npy"), np.zeros(1))
    """)
    cfg = SparseConfig.load(str(out / CONFIG_FILENAME))
    assert cfg.enabled and cfg.reduction == 0.75 and cfg.feature == "raw"


def test_doubletake_sparse_config_goes_to_the_derived_folder_not_the_newest(tmp_path):
    """Without --output_dir: the folder upstream derives from the args gets sparse_config.json,
    even when another DoubleTake folder beside the checkpoint got a results.npy later."""
    run = tmp_path / "run"
    run.mkdir()
    exact = "DoubleTake_samples_run_000000100_seed4_handshake_20_double_take_blend_5_skipSteps_100"
    _sampling_run(tmp_path, 'model_path="run/model000000100.pt", output_dir="", input_text="", seed=4, '
                              "sample_gt=False, double_take=True, handshake_size=20, skip_steps_double_take=100", f"""
        for name in ({exact!r}, "DoubleTake_samples_other"):   # the second one written last: the newest
            os.makedirs(os.path.join("run", name))
            np.save(os.path.join("run", name, "results.npy"), np.zeros(1))
            time.sleep(0.05)
    """)
    assert SparseConfig.load(str(run / exact / CONFIG_FILENAME)).reduction == 0.75
    assert not (run / "DoubleTake_samples_other" / CONFIG_FILENAME).exists()


def _mdm_args(**kw):
    base = dict(model_path="save/my_model/model000200000.pt", output_dir="", seed=10, text_prompt="", input_text="",
                dynamic_text_path="")
    return argparse.Namespace(**{**base, **kw})


def _edit_args(**kw):
    base = dict(model_path="save/my_model/model000200000.pt", output_dir="", seed=10, edit_mode="in_between",
                text_condition="")
    return argparse.Namespace(**{**base, **kw})


@pytest.mark.parametrize("args,name", [
    (_mdm_args(), "samples_my_model_000200000_seed10"),
    (_mdm_args(seed=3, text_prompt="a person. jumps"), "samples_my_model_000200000_seed3_a_person_jumps"),
    (_mdm_args(input_text="texts/my prompts.v2.txt"), "samples_my_model_000200000_seed10_my_promptsv2"),
    (_mdm_args(dynamic_text_path="d/dyn.txt"), "samples_my_model_000200000_seed10_dyn"),
    (_mdm_args(text_prompt="walk", input_text="x.txt"), "samples_my_model_000200000_seed10_walk"),
    (_edit_args(), "edit_my_model_000200000_in_between_seed10"),
    (_edit_args(edit_mode="upper_body", seed=4, text_condition="wave. hands"),
     "edit_my_model_000200000_upper_body_seed4_wave_hands"),
])
def test_mdm_sample_output_dir_is_derived_from_the_args_as_upstream_does(args, name):
    """Expected names written out by hand from MDM's sample/generate.py and sample/edit.py (d4fd88c)."""
    assert sample_output_dir(args) == os.path.abspath(os.path.join("save", "my_model", name))


def test_mdm_sample_output_dir_given_or_none():
    assert sample_output_dir(_mdm_args(output_dir="res/x")) == os.path.abspath("res/x")
    assert sample_output_dir(argparse.Namespace(model_path="m/model1.pt", eval_mode="wo_mm")) is None  # eval_humanml
    assert sample_output_dir(_mdm_args(model_path=None)) is None


_WRITE_RESULTS = """
os.makedirs(OUT, exist_ok=True)   # what sample.generate / sample.edit do at the end (rmtree, makedirs)
np.save(os.path.join(OUT, "results.npy"), np.zeros(1))
"""


@pytest.mark.parametrize("model", ["TinyMDM", "DiP"])
def test_mdm_sparse_sampling_writes_sparse_config_beside_its_results(tmp_path, model):
    """sample.generate (MDM, DiP) with a sparse checkpoint: the folder of results.npy gets the config
    that sampled it, so a sparse results.npy can be told from a dense one afterwards."""
    out = tmp_path / "out"
    _sampling_run(tmp_path, f"model_path={str(tmp_path / 'model000001.pt')!r}, output_dir={str(out)!r}",
                  f"OUT = {str(out)!r}" + _WRITE_RESULTS, model=model, entry="mdm")
    cfg = SparseConfig.load(str(out / CONFIG_FILENAME))
    assert cfg.enabled and cfg.reduction == 0.75 and cfg.prefix_frames == (20 if model == "DiP" else 0)


def test_mdm_zero_shot_edit_writes_sparse_config_in_the_derived_folder(tmp_path):
    """sample.edit --sparse_preset zero_shot on a dense checkpoint, no --output_dir: the folder edit
    derives from its options gets the preset's settings."""
    (tmp_path / "run").mkdir()
    out = tmp_path / "run" / "edit_run_000000100_in_between_seed4_jump"
    _sampling_run(tmp_path, 'model_path="run/model000000100.pt", output_dir="", seed=4, edit_mode="in_between", '
                            'text_condition="jump", sparse_preset="zero_shot"',
                  f"OUT = {str(out)!r}" + _WRITE_RESULTS, model="TinyMDM", entry="mdm", sparse=False)
    cfg = SparseConfig.load(str(out / CONFIG_FILENAME))
    assert cfg.fsq is False and cfg.lipschitz is False and cfg.dynamic_update is False


def test_dense_sampling_and_failed_sampling_write_no_sparse_config(tmp_path):
    out = tmp_path / "out"
    _sampling_run(tmp_path, f"model_path='m/model1.pt', output_dir={str(out)!r}", f"OUT = {str(out)!r}" +
                  _WRITE_RESULTS, model="TinyMDM", entry="mdm", sparse=False)
    assert (out / "results.npy").exists() and not (out / CONFIG_FILENAME).exists()     # dense: upstream's files
    failed = tmp_path / "failed"
    _sampling_run(tmp_path, f"model_path='m/model1.pt', output_dir={str(failed)!r}", "", model="TinyMDM", entry="mdm")
    assert not failed.exists()                                                          # no results.npy: nothing


def test_a_sparse_config_json_already_there_is_never_overwritten(tmp_path):
    """Another config already in the results folder stays as it is; the run says so in one smdm:
    line on stderr, even with warnings captured by logging (moviepy's set-up in MDM)."""
    out = tmp_path / "out"
    out.mkdir()
    theirs = SparseConfig(reduction=0.5)
    theirs.save(str(out / CONFIG_FILENAME))
    before = (out / CONFIG_FILENAME).read_bytes()
    proc = _sampling_run(tmp_path, f"model_path='m/model1.pt', output_dir={str(out)!r}", f"OUT = {str(out)!r}" +
                         _WRITE_RESULTS, model="TinyMDM", entry="mdm",
                         extra="import logging; logging.captureWarnings(True)")
    assert (out / CONFIG_FILENAME).read_bytes() == before
    lines = [ln for ln in proc.stderr.splitlines() if CONFIG_FILENAME in ln]
    assert len(lines) == 1 and lines[0].startswith(f"smdm: {CONFIG_FILENAME} not written beside "), proc.stderr
    assert "differs in reduction" in lines[0]


def test_motiondiffuse_opt_txt_states_fsq_off_with_a_warning(tmp_path):
    from smdm_plugin.families.motiondiffuse.upstream import attach_trainer, config_from_opt

    parser = argparse.ArgumentParser()
    add_sparse_options(parser)
    opt = parser.parse_args(["--sparse", "--sparse_feature", "raw", "--sparse_fsq", "true"])
    opt.is_train, opt.model_dir = True, str(tmp_path / "exp" / "model")
    os.makedirs(opt.model_dir)
    opt_file = tmp_path / "exp" / "opt.txt"
    with open(opt_file, "w") as f:  # as MotionDiffuse's BaseOptions.parse writes it
        f.write("------------ Options -------------\n")
        for k, v in sorted(vars(opt).items()):
            f.write("%s: %s\n" % (str(k), str(v)))
        f.write("-------------- End ----------------\n")
    assert "sparse_fsq: True" in opt_file.read_text()

    class Trainer:
        def __init__(self):
            self.encoder, self.diffusion, self.opt = StandInMotionTransformer(), StandInDiffusion(), opt

    with pytest.warns(UserWarning, match="fsq=True cannot apply"):
        attach_trainer(Trainer())
    text = opt_file.read_text()
    assert "sparse_fsq: False" in text and "sparse_fsq: True" not in text
    lines = text.splitlines()
    assert lines[0].startswith("------------ Options") and lines[-1].startswith("-------------- End")
    assert SparseConfig.load(os.path.join(opt.model_dir, CONFIG_FILENAME)).fsq is False
    # read back as MotionDiffuse's get_opt does (key: value strings): the files agree, FSQ included
    read = argparse.Namespace(**{k: v for k, v in (ln.split(": ", 1) for ln in lines[1:-1])})
    read.is_train, read.model_dir = False, opt.model_dir
    saved = config_from_opt(read)
    from smdm_plugin.families.motiondiffuse.upstream import _options
    assert disagreement(saved, _options(read), "sparse_config.json", str(opt_file), ignore=("version",)) is None


def test_doubletake_196_frame_mask_no_warning_lengths_from_the_window():
    """priorMDM passes y['mask'] [S, 1, 1, 196] to both takes; the window is 40 frames here: no
    mask-length warning, and the valid frames are y['lengths'] (not cut from 196)."""
    from smdm_plugin.families.doubletake.model import doubletake_window_mask

    torch.manual_seed(0)
    model = doubleTake_TinyMDM(njoints=8, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, cond_mode="no_cond")
    _quiet(sparsify_priormdm, model, argparse.Namespace(sparse=True, sparse_feature="raw", blend_len=5))
    seen = []
    tr = model.seqTransEncoder
    orig = tr.set_plan
    tr.set_plan = lambda plan: (seen.append(plan), orig(plan))[1]
    lens = torch.tensor([40, 30])
    trans = torch.zeros(2, 40)
    trans[0, 34:40] = 1
    trans[1, :6] = 1
    y = {"lengths": lens, "mask": torch.ones(2, 1, 1, 196), "is_transition": trans}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with torch.no_grad():
            model(torch.randn(2, 8, 1, 40), torch.tensor([5, 5]), y)
    plan = [p for p in seen if p is not None][-1]
    assert not plan.mask[1, 30:].any() and plan.mask[1, 29] and plan.mask[0, 39]  # lengths 40 / 30
    assert y["mask"].shape[-1] == 196  # the caller's y is untouched
    want = torch.arange(40)[None] < lens[:, None]
    assert torch.equal(doubletake_window_mask(y, 2, 40).view(2, 40), want)
    assert doubletake_window_mask({"lengths": lens, "mask": torch.ones(2, 1, 1, 196)}, 2, 40) is None  # not DoubleTake
