"""The one reader of a HumanML3D-format folder (io.humanml3d.load_humanml3d) against the files
themselves, and what its callers (MotionSet.from_split, MotionData, load_captioned) make of it."""
from __future__ import annotations

import numpy as np
import pytest

from smdm_plugin.io.humanml3d import load_humanml3d
from smdm_plugin.training.data import MotionData, MotionSet
from helpers.synthetic_data import write_humanml3d


@pytest.fixture()
def folder(tmp_path):
    root = write_humanml3d(tmp_path / "d", train=(60, 30, 48, 70), val=(44, 56))
    (root / "train.txt").write_text("train000\nmissing\ntrain001\ntrain002\ntrain003\n")  # an id without a file
    (root / "texts").mkdir()
    (root / "texts" / "train000.txt").write_text("a man walks.#a/DET man/NOUN walk/VERB#0.0#0.0\n"
                                                  "he waves.#he/PRON wave/VERB#0.5#2.5\n")
    return root


def test_reads_skips_and_cuts_as_the_files_say(folder):
    s = load_humanml3d(str(folder), "train", 50, 40, joints=True, captions=True)
    assert s.ids == ["train000", "train002", "train003"]  # 'missing' has no file, train001 is 30 < 40 frames
    for name, motion, joints in zip(s.ids, s.motions, s.joints):
        raw = np.load(folder / "new_joint_vecs" / f"{name}.npy")
        np.testing.assert_array_equal(motion, raw[:50])
        np.testing.assert_array_equal(joints, np.load(folder / "new_joints" / f"{name}.npy")[:50])
    assert [len(c) for c in s.captions] == [2, 0, 0] and s.captions[0][1].start == 0.5
    # every file read, the short motion's included (a fingerprint must change when it does)
    assert str(folder / "new_joint_vecs" / "train001.npy") in s.files
    assert str(folder / "texts" / "train000.txt") in s.files
    whole = load_humanml3d(str(folder), "train", None, 40)
    assert [len(m) for m in whole.motions] == [60, 48, 70] and whole.joints is None and whole.captions is None


def test_bad_input_is_one_line_naming_the_file(folder):
    with pytest.raises(FileNotFoundError, match=r"is not a HumanML3D-format folder \(missing test.txt\)"):
        load_humanml3d(str(folder), "test")
    np.save(folder / "new_joint_vecs" / "train002.npy", np.full((48, 263), np.nan, np.float32))
    with pytest.raises(ValueError, match=r"train002\.npy"):
        load_humanml3d(str(folder), "train")
    with pytest.raises(ValueError, match="no motion of >= 100 frames"):
        load_humanml3d(str(folder), "val", 196, 100)


def test_callers_normalise_and_require_captions(folder):
    s = load_humanml3d(str(folder), "train", 50, 40, captions=True)
    m = MotionSet.from_split(s)
    x, L = m.padded([0])
    np.testing.assert_allclose(x[0, :50].numpy(), (s.motions[0] - s.mean) / s.std)
    with pytest.raises(FileNotFoundError, match=r"train002\.txt: missing or empty"):
        MotionSet.from_split(s, captions=True)
    data = MotionData(str(folder), 50)
    assert data.train.ids == s.ids and data.val.ids == ["val000", "val001"] and data.val.joints[0].shape == (44, 22, 3)
    assert data.files == sorted(set(data.files)) and len(data.fingerprint) == 16
