"""What ``smdm eval`` and ``smdm inbetween`` read is checked before it is used, one line naming the file
(exit status 2): a model folder whose files disagree or whose text encoder is missing, motion files with
absurd values. (The loaders themselves: tests/training/test_load_validation.py; the readers:
tests/io/test_readers.py.)"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from smdm_plugin.apps.cli import main as smdm
from smdm_plugin.metrics.evaluator.data import load_split

from helpers.commands import TINY_TRAIN
from helpers.synthetic_data import write_humanml3d


@pytest.fixture(scope="module")
def evaluator(tmp_path_factory) -> str:
    """A tiny evaluator of the embedded clips (joints66), trained in seconds."""
    out = tmp_path_factory.mktemp("ev") / "ev"
    assert smdm(["evaluator", "train", "--out", str(out), "--epochs", "1", "--ae-epochs", "1", "--hidden", "16",
                 "--dim", "8", "--no-progress", "--threads", "1"]) == 0
    return str(out)


@pytest.fixture
def text_model(tmp_path) -> Path:
    """A sparse, text-conditioned joints66 model (`smdm train --sparse --text`), as the evaluator reads."""
    data = write_humanml3d(tmp_path / "d66", dim=66, captions=True)
    out = tmp_path / "model"
    assert smdm(["train", "--data", str(data), "--out", str(out), "--min-frames", "20", *TINY_TRAIN, "--steps", "1",
                 "--sparse", "--text"]) == 0
    return out


def _edit_json(path: Path, **changes) -> None:
    path.write_text(json.dumps({**json.loads(path.read_text()), **changes}))


def _refused(argv, capsys) -> str:
    """The one line of a command refused with exit status 2 (argparse's usage lines aside)."""
    try:
        rc = smdm(argv)
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err and "Traceback" not in "\n".join(err), err
    return err[-1]


def _eval(evaluator: str, model: Path, out: Path) -> list:
    return ["eval", "--evaluator", evaluator, "--model", str(model), "--out", str(out), "--replications", "1",
            "--no-progress", "--threads", "1"]


def test_eval_and_inbetween_refuse_a_model_whose_configs_disagree(evaluator, text_model, tmp_path, capsys):
    """0.7.0 sampled it as the edited sparse_config.json said (50% dropped), exit 0."""
    _edit_json(text_model / "sparse_config.json", reduction=0.5, selector="uniform")
    want = (r"train_config.json and .*sparse_config.json disagree: reduction: train_config.json 0.8, "
            r"sparse_config.json 0.5; selector: train_config.json 'vw', sparse_config.json 'uniform'")
    import re

    assert re.search(want, _refused(_eval(evaluator, text_model, tmp_path / "r"), capsys))
    keyframes = tmp_path / "d66" / "new_joints" / "train000.npy"
    line = _refused(["inbetween", "--model", str(text_model), "--keyframes", str(keyframes), "--every", "10",
                     "--out", str(tmp_path / "ib"), "--no-gif", "--threads", "1"], capsys)
    assert re.search(want, line) and line.startswith("smdm inbetween: error: --model")
    assert not (tmp_path / "r").exists() and not (tmp_path / "ib").exists()


def test_eval_refuses_a_text_model_without_its_text_encoder(evaluator, text_model, tmp_path, capsys):
    """0.7.0 sampled it unconditionally and wrote "the model is unconditional (trained without text)"."""
    (text_model / "text_encoder.json").unlink()
    line = _refused(_eval(evaluator, text_model, tmp_path / "r"), capsys)
    assert line.startswith(f"smdm eval: {text_model / 'text_encoder.json'}: missing, but ")
    assert "backbone.json says cond_mode 'text'" in line and not (tmp_path / "r").exists()


def test_eval_motions_with_absurd_values_are_one_line(evaluator, tmp_path, capsys):
    """0.7.0: a float32 motion scaled by 1e30 scored, exit 0, jitter null."""
    test = load_split(None, "test")
    folder = tmp_path / "m"
    folder.mkdir()
    for i, m in zip(test.ids, test.motions):
        np.save(folder / f"{i}.npy", m.astype(np.float32))
    bad = folder / f"{test.ids[3]}.npy"
    np.save(bad, (np.load(bad) * np.float32(1e30)).astype(np.float32))
    line = _refused(["eval", "--evaluator", evaluator, "--motions", str(folder), "--out", str(tmp_path / "r"),
                     "--protocol", "fixed", "--threads", "1"], capsys)
    assert line.startswith(f"smdm eval: {bad}: motion features reach ") and "at index [" in line
    assert "(beyond ±1e+07)" in line and not (tmp_path / "r").exists()
