"""What the plugin says inside an upstream run reaches the user and is true (issue 40).

* Its warnings (a setting that cannot apply, a fallback, a deviation from the paper) reach stderr,
  and upstream's log, as one ``smdm: ...`` line under every logging set-up an upstream run has:
  MDM imports moviepy 1.0.3, whose ``ffmpeg_reader`` calls ``logging.captureWarnings(True)`` (every
  Python warning to the ``py.warnings`` logger, which has no handler in MDM's scripts), a user may
  add handlers (a log file, the terminal), or nothing captures at all. Upstream's own warnings are
  shown as before.
* The ON line says what the run does per phase: a zero-shot wrap samples with a uniform mask and
  draws no training mask noise.
* MotionDiffuse runs without FSQ keys by default, with no warning; asking for them still warns.
"""
import argparse
import logging
import os
import subprocess
import sys
import textwrap
import warnings

import pytest
import torch

from smdm_plugin import SparseConfig, TinyMDM, sparse_config_of
from smdm_plugin.integrations import messages
from smdm_plugin.integrations.announce import describe_run
from smdm_plugin.families.mdm.upstream import apply_compile, sparsify_mdm, warn_if_upstream_steps
from smdm_plugin.families.motiondiffuse.upstream import add_sparse_options as add_motiondiffuse_options
from smdm_plugin.families.motiondiffuse.upstream import attach_trainer

from smdm_plugin.families.motiondiffuse.standin import StandInDiffusion, StandInMotionTransformer
from helpers.paths import ROOT

STEPS_LINE = "smdm: sparse training at 1000 diffusion steps"
FSQ_LINE = "smdm: sparsify: MotionDiffuse's self-attention is linear"
COMPILE_LINE = "smdm: compile: reduce-overhead needs CUDA graphs"


def _tiny(**kw) -> TinyMDM:
    return TinyMDM(njoints=8, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, cond_mode="no_cond", **kw)


class _Trainer:
    """What ``attach_trainer`` reads of MotionDiffuse's ``DDPMTrainer``."""

    def __init__(self, opt: argparse.Namespace) -> None:
        self.encoder, self.diffusion, self.opt = StandInMotionTransformer(), StandInDiffusion(), opt


def _motiondiffuse_opt(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_motiondiffuse_options(parser)
    opt = parser.parse_args(["--sparse", "--sparse_feature", "raw", *argv])
    opt.is_train = False
    return opt


def _default_impl(msg: "warnings.WarningMessage") -> None:
    """Python's own way of showing a warning (what runs outside pytest's recording)."""
    sys.stderr.write(warnings._formatwarnmsg(msg))


@pytest.fixture
def upstream_warnings(monkeypatch):
    """The warnings module as in an upstream run (not recorded by pytest, Python's default filter)
    with the integrations' hook installed; yields a function that sets up logging the way
    upstream / the user does: ``logging_as("none" | "moviepy" | "moviepy+file" | "moviepy+stderr")``
    (returns the log file of ``moviepy+file``). Everything is put back afterwards."""
    monkeypatch.setattr(warnings, "_showwarnmsg", warnings._showwarnmsg)   # restored after the test
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    with warnings.catch_warnings():
        monkeypatch.setattr(warnings, "_showwarnmsg_impl", _default_impl)
        monkeypatch.setattr(warnings, "showwarning", warnings._showwarning_orig)
        warnings.simplefilter("default")
        messages.show_plugin_warnings()

        def logging_as(kind: str, log_file: str = "") -> str:
            if kind.startswith("moviepy"):
                logging.captureWarnings(True)          # moviepy/video/io/ffmpeg_reader.py, at import
            if kind == "moviepy+file":
                handler = logging.FileHandler(log_file)
            elif kind == "moviepy+stderr":
                handler = logging.StreamHandler(sys.stderr)
            else:
                return ""
            handler.setFormatter(logging.Formatter(logging.BASIC_FORMAT))   # as logging.basicConfig does
            root.addHandler(handler)
            root.setLevel(logging.INFO)
            return log_file if kind == "moviepy+file" else ""

        try:
            yield logging_as
        finally:
            logging.captureWarnings(False)
            for h in root.handlers[:]:
                if h not in handlers:
                    root.removeHandler(h)
                    h.close()
            root.setLevel(level)


def _plugin_warnings(tmp_path) -> None:
    """Three plugin warnings through the integrations, and one of upstream's own."""
    warn_if_upstream_steps(SparseConfig(), 1000)                            # a deviation from the paper
    opt = _motiondiffuse_opt("--sparse_fsq", "true")                        # a setting that cannot apply
    attach_trainer(_Trainer(opt))
    from smdm_plugin.runtime.compile import compile_model, uncompile  # a fallback

    model = _tiny()
    compile_model(model, "reduce-overhead", device="cpu")
    uncompile(model)
    warnings.warn("upstream's own warning")


def _smdm_lines(text: str) -> list:
    return [ln for ln in text.splitlines() if "smdm:" in ln]


@pytest.mark.parametrize("kind", ["none", "moviepy", "moviepy+file", "moviepy+stderr"])
def test_plugin_warnings_reach_stderr_and_the_log_as_one_smdm_line(kind, upstream_warnings, capsys, tmp_path):
    log = upstream_warnings(kind, str(tmp_path / "upstream.log"))
    _plugin_warnings(tmp_path)
    err = capsys.readouterr().err
    for line in (STEPS_LINE, FSQ_LINE, COMPILE_LINE):
        on_stderr = [ln for ln in err.splitlines() if line in ln]
        assert len(on_stderr) == 1, (kind, line, err)
        if kind == "moviepy+stderr":                  # through upstream's handler (its format), once
            assert on_stderr[0].startswith("WARNING:py.warnings:smdm: ")
        else:
            assert on_stderr[0].startswith("smdm: ")
    assert "UserWarning" not in "".join(_smdm_lines(err))       # one line each, not Python's two
    if log:
        logged = open(log).read()
        assert all(sum(line in ln for ln in logged.splitlines()) == 1 for line in (STEPS_LINE, FSQ_LINE,
                                                                                     COMPILE_LINE)), logged
    # upstream's own warning is shown (or captured) as upstream's set-up says: untouched
    if kind == "none":
        assert "UserWarning: upstream's own warning" in err
    elif kind == "moviepy":
        assert "upstream's own warning" not in err
    elif kind == "moviepy+file":
        assert "UserWarning: upstream's own warning" in open(log).read()


def test_recorded_warnings_are_left_to_the_recorder(upstream_warnings, capsys):
    """Inside ``catch_warnings(record=True)`` (pytest.warns, a library user) nothing is printed and
    the warning is recorded as issued."""
    with pytest.warns(UserWarning, match="1000 diffusion steps"):
        warn_if_upstream_steps(SparseConfig(), 1000)
    assert "smdm" not in capsys.readouterr().err


def test_a_warning_is_the_plugins_by_where_it_was_issued_or_its_category():
    class PluginWarning(UserWarning):
        pass

    PluginWarning.__module__ = "smdm_plugin.io.bvh"
    here = sys._getframe()
    mk = warnings.WarningMessage
    assert not messages.is_plugin_warning(mk("x", UserWarning, "f.py", 1), here)
    assert messages.is_plugin_warning(mk("x", PluginWarning, "f.py", 1), here)
    assert messages.one_line("smdm compile: a\nb") == "smdm: compile: a b"
    assert messages.one_line("y['mask'] covers 1 frames") == "smdm: y['mask'] covers 1 frames"
    assert messages.one_line("smdm: done") == "smdm: done"


def _child(cwd, script: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-c", textwrap.dedent(script)], env=env, cwd=str(cwd),
                          capture_output=True, text=True, timeout=300)


def test_an_mdm_run_under_moviepys_capture_shows_the_plugins_warnings(tmp_path):
    """A fresh interpreter set up as MDM's train script is by the time it builds the model (moviepy
    imported: warnings captured by logging, no handler), calling the plugin where the patch does:
    each warning is one ``smdm:`` line on stderr (0.7.0 printed nothing)."""
    proc = _child(tmp_path, f"""
        import argparse, logging, os
        logging.captureWarnings(True)                 # moviepy 1.0.3, imported by sample/generate.py
        from smdm_plugin import TinyMDM
        from smdm_plugin.runtime.compile import add_compile_options
        from smdm_plugin.integrations.options import add_sparse_options
        from smdm_plugin.reference.simple_diffusion import SimpleDiffusion
        parser = argparse.ArgumentParser()
        add_compile_options(parser.add_argument_group("base"))
        add_sparse_options(parser.add_argument_group("model"))
        args = parser.parse_args(["--sparse", "--sparse_feature", "raw", "--sparse_compile", "reduce-overhead"])
        args.save_dir, args.diffusion_steps = "run", 1000
        os.makedirs("run")
        from smdm_plugin.families.mdm.upstream import sparsify_mdm
        m = TinyMDM(njoints=8, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, cond_mode="no_cond")
        sparsify_mdm(m, args, None, SimpleDiffusion(1000))
    """)
    assert proc.returncode == 0, proc.stderr
    lines = _smdm_lines(proc.stderr)
    assert sum(STEPS_LINE in ln for ln in lines) == 1, proc.stderr
    if not torch.cuda.is_available():
        assert sum(COMPILE_LINE in ln for ln in lines) == 1, proc.stderr
    assert "UserWarning" not in proc.stderr, proc.stderr          # one line each, not Python's format


# --------------------------------------------------------------------------- the ON line
def _sampling_args(**kw) -> argparse.Namespace:
    base = dict(sparse=False, model_path="save/dense/model000001000.pt", sparse_preset="zero_shot")
    return argparse.Namespace(**{**base, **kw})


def _on_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if "sparse keyframe mode ON" in ln]
    assert len(lines) == 1, err
    return lines[0]


def test_zero_shot_wrap_says_it_samples_with_a_uniform_mask_and_no_training_noise(capsys):
    """``sample.generate --sparse_preset zero_shot`` on a dense checkpoint: uniform keyframes at
    every step, the preset's linear fill, no FSQ / Lipschitz layers; nothing about VW or mask
    noise, which act on training only (0.7.0 said "vw keyframes, mask noise 0.1")."""
    m = _tiny()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")                # (no dataset Mean/Std here)
        sparsify_mdm(m, _sampling_args(sparse_preset=None), None, None)
        assert "sparse keyframe mode" not in capsys.readouterr().err     # a dense run: no line
        sparsify_mdm(m, _sampling_args(), None, None)
    line = _on_line(capsys.readouterr().err)
    assert not [k for k in vars(m) if k.startswith("_smdm") and k != "_smdm_state"]   # nothing put on the model
    assert line.startswith("smdm: sparse keyframe mode ON (MDM/DiP, sampling): reduction 0.8 (80% of the frames "
                           "dropped); sampling: ")
    assert "sampling: uniform keyframes at every step (dynamic update off), linear fill" in line
    assert "FSQ keys off" in line and "Lipschitz MLPs off" in line
    assert "vw" not in line and "mask noise" not in line and "training" not in line


def test_a_training_run_states_both_phases_once(capsys, tmp_path):
    args = argparse.Namespace(sparse=True, sparse_feature="raw", sparse_dynamic_update=True, sparse_gamma=0.1,
                              sparse_mask_noise=0.2, save_dir=str(tmp_path / "run"), overwrite=False)
    os.makedirs(args.save_dir)
    m = TinyMDM(njoints=8, nfeats=1, latent_dim=32, ff_size=64, num_layers=1, cond_mode="no_cond",
                context_len=20, pred_len=40)
    from smdm_plugin.reference.simple_diffusion import SimpleDiffusion

    for _ in range(2):                                   # patch + launcher both call it
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sparsify_mdm(m, args, None, SimpleDiffusion(50))
    line = _on_line(capsys.readouterr().err)
    cfg = sparse_config_of(m)
    assert line == f"smdm: sparse keyframe mode ON (MDM/DiP, training): {describe_run(cfg, True, 5, 8)}"
    assert "training: vw keyframes from x0, mask noise 0.2" in line
    assert "sampling: uniform keyframes, then vw on x_t in the last 5 of 50 steps, cubic fill" in line
    assert "20 prefix frames dense" in line and "T 50" in line


def test_the_fill_and_the_phases_are_described_as_they_run():
    c = SparseConfig(reduction=0.5, selector="uniform", mask_noise=0.0, interpolate=False,
                     sample_interpolation="cubic", sample_interpolation_steps=3, diffusion_steps=10)
    text = describe_run(c, True, 0, None)
    assert "training: uniform keyframes from x0, no mask noise, loss on keyframes only" in text
    assert "cubic in the last 3 steps, linear before fill" in text
    assert "fill auto (linear for HumanML3D/KIT" not in text
    auto = describe_run(SparseConfig(), False, 0, None)
    assert "auto (linear for HumanML3D/KIT features, cubic for raw) fill" in auto
    assert describe_run(SparseConfig(), False, 0, 263).split("; ")[1].endswith("linear fill")
    assert "every frame a keyframe" in describe_run(SparseConfig(reduction=0.0), False, 0, 263)


# --------------------------------------------------------------------------- MotionDiffuse: no FSQ keys by default
def test_motiondiffuse_runs_without_fsq_keys_by_default_and_says_nothing_about_it(tmp_path):
    opt = _motiondiffuse_opt()
    assert opt.sparse_fsq is False
    opt.is_train, opt.model_dir = True, str(tmp_path / "exp" / "model")
    os.makedirs(opt.model_dir)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        trainer = attach_trainer(_Trainer(opt))
    assert not [w for w in caught if "fsq" in str(w.message).lower()], [str(w.message) for w in caught]
    assert sparse_config_of(trainer.encoder).fsq is False
    assert SparseConfig.load(os.path.join(opt.model_dir, "sparse_config.json")).fsq is False
    parser = argparse.ArgumentParser()
    add_motiondiffuse_options(parser)                    # --help says which default and why
    assert parser._option_string_actions["--sparse_fsq"].help.endswith(
        "(default False: MotionDiffuse's self-attention is linear: FSQ keys cannot apply)")


def test_motiondiffuse_options_files_without_the_fsq_key_mean_no_fsq_keys():
    """An ``opt.txt`` written before the option existed has no ``sparse_fsq`` line: MotionDiffuse's
    default, not the dataclass's, and no warning."""
    from smdm_plugin.families.motiondiffuse.upstream import config_from_opt

    opt = argparse.Namespace(sparse="True", sparse_reduction="0.8", is_train=False, model_dir=None)
    assert config_from_opt(opt).fsq is False


def test_explicit_fsq_on_motiondiffuse_still_warns():
    with pytest.warns(UserWarning, match="fsq=True cannot apply"):
        trainer = attach_trainer(_Trainer(_motiondiffuse_opt("--sparse_fsq", "true")))
    assert sparse_config_of(trainer.encoder).fsq is False
