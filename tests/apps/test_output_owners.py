"""A folder another command wrote is never taken for the command's own: ``smdm train --out`` on
``smdm inbetween``'s or a saved model's folder is refused (0.10.6 deleted their files: the manifest
listed every entry, and whose manifest it was went unread), ``--resume`` on another command's run is
refused, ``--overwrite`` still replaces; ``--resume`` of a run whose ``train_state.pt`` is gone but
whose checkpoints are there is refused (0.10.6 started over at step 0 beside them)."""
from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from smdm_plugin.io.outdir import MANIFEST, OutputDir, OutputExistsError

from helpers.commands import smdm, snapshot, train


def written_by(folder: Path, command: str, *names: str) -> dict:
    """A finished output of ``command`` (its manifest lists ``names``); its snapshot."""
    folder.mkdir()
    for n in names:
        (folder / n).write_text(n)
    (folder / MANIFEST).write_text(json.dumps({"command": command, "entries": sorted(names)}))
    return snapshot(folder)


def test_another_commands_folder_is_not_taken_for_ones_own(tmp_path):
    out = tmp_path / "ib"
    before = written_by(out, "smdm inbetween", "dense_00.npy", "summary.md")
    with pytest.raises(OutputExistsError, match="holds the output of smdm inbetween, not of smdm train; pass "
                                                "--overwrite"):
        OutputDir(out, command="smdm train", resumable=True).check()
    with pytest.raises(OutputExistsError, match="not a run of smdm train to resume"):
        OutputDir(out, command="smdm train", resumable=True, resume=True).check()
    assert snapshot(out) == before
    # the command's own finished output is still recognised, and --overwrite replaces another's
    OutputDir(out, command="smdm inbetween", overwrite=True).check()
    OutputDir(out, command="smdm train", resumable=True, overwrite=True).check()


def test_smdm_train_never_deletes_another_commands_output(tmp_path, synthetic_hml):
    out = tmp_path / "model"
    before = written_by(out, "save_bundle", "model.pt", "motion.json", "backbone.json")
    r = smdm("train", "--data", synthetic_hml, "--out", out, "--steps", "1", "--min-frames", "20",
             "--latent-dim", "16", "--layers", "1", "--heads", "2", "--ff-size", "32", "--batch", "2",
             "--diffusion-steps", "5", "--threads", "1", "--quiet")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert "holds the output of save_bundle, not of smdm train" in r.stderr.strip().splitlines()[-1]
    assert snapshot(out) == before


def test_resume_without_the_training_state_is_refused_not_restarted(tmp_path, synthetic_hml):
    out = tmp_path / "run"
    assert train(synthetic_hml, out, "--steps", "4", "--save-every", "2") == 0
    os.unlink(out / "train_state.pt")
    before = {k: v for k, v in snapshot(out).items() if k != MANIFEST}     # (its listing follows the files)
    r = smdm("train", "--data", synthetic_hml, "--out", out, "--steps", "6", "--resume", "--min-frames", "20",
             "--latent-dim", "16", "--layers", "1", "--heads", "2", "--ff-size", "32", "--batch", "2",
             "--diffusion-steps", "10", "--threads", "1", "--quiet")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert "holds checkpoints (model000000002.pt, model000000004.pt) but no train_state.pt" in r.stderr
    assert {k: v for k, v in snapshot(out).items() if k != MANIFEST} == before
