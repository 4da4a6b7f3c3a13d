"""The io layer's readers: motion files (empty, complex, beyond float32's range, absurd positions) and the
other files of a HumanML3D-format folder (joints, captions) are refused in one line naming the file; data
known by content (file digests)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from smdm_plugin.apps.common.motion_files import load_motion
from smdm_plugin.io.files import describe_changes, digests_fingerprint, file_digests
from smdm_plugin.io.validate import check_array, load_feature_motion


# ------------------------------------------------------------------------------ readers
@pytest.fixture
def motions(tmp_path) -> Path:
    rng = np.random.default_rng(0)
    open(tmp_path / "empty.npy", "wb").close()
    np.save(tmp_path / "complex.npy", (rng.random((30, 22, 3)) + 1j).astype(np.complex64))
    big = rng.random((30, 22, 3))
    big[3, 2, 1] = 1e300
    np.save(tmp_path / "beyond_f32.npy", big)
    absurd = rng.random((30, 22, 3))
    absurd[5] = 1e30
    np.save(tmp_path / "absurd.npy", absurd)
    features = rng.random((30, 263)).astype(np.float32)
    features[7, 100] = 1e30  # finite in float32; HumanML3D features of a real motion are far below 1e7
    np.save(tmp_path / "absurd_features.npy", features)
    return tmp_path


@pytest.mark.parametrize("name, match", [
    ("empty.npy", "empty.npy: not a readable .npy file"),
    ("complex.npy", "complex.npy: expected real numbers, got dtype complex64"),
    ("beyond_f32.npy", "beyond_f32.npy: holds 1e\\+300, beyond float32's range"),
    ("absurd.npy", r"absurd.npy: joint positions reach 1e\+30 at index \[5, 0, 0\] \(beyond ±1e\+07\)"),
    ("absurd_features.npy", r"absurd_features.npy: features reach 1e\+30 at index \[7, 100\]"),
])
def test_load_motion_refuses_unusable_files_in_one_line(motions, name, match):
    with pytest.raises(ValueError, match=match) as e:
        load_motion(str(motions / name))
    assert "\n" not in str(e.value)


def test_a_sample_of_a_file_of_one_motion_is_refused_not_ignored(tmp_path):
    """0.10.5 read ``--sample 5`` of a file holding one motion as its motion (the option dropped
    silently); a batched file gives the sample asked for."""
    rng = np.random.default_rng(1)
    one, batch = rng.random((30, 22, 3)), rng.random((3, 30, 22, 3))
    np.save(tmp_path / "one.npy", one)
    np.save(tmp_path / "batch.npy", batch)
    np.testing.assert_allclose(load_motion(str(tmp_path / "one.npy"), sample=0).joints, one)
    with pytest.raises(ValueError, match=r"one.npy holds one motion: --sample 2 applies to batched files only"):
        load_motion(str(tmp_path / "one.npy"), sample=2)
    np.testing.assert_allclose(load_motion(str(tmp_path / "batch.npy"), sample=2).joints, batch[2])
    with pytest.raises(ValueError, match=r"sample must be in \[0, 3\)"):
        load_motion(str(tmp_path / "batch.npy"), sample=3)
    (tmp_path / "one.bvh").write_text("HIERARCHY\n")
    with pytest.raises(ValueError, match=r"one.bvh holds one motion: --sample 1"):
        load_motion(str(tmp_path / "one.bvh"), sample=1)


def test_feature_motion_loader_for_eval_motions(tmp_path):
    """The shared loader of `smdm eval --motions` files (io.validate.load_feature_motion)."""
    open(tmp_path / "empty.npy", "wb").close()
    with pytest.raises(ValueError, match="empty.npy: not a readable .npy file"):
        load_feature_motion(str(tmp_path / "empty.npy"), 66)
    a = np.zeros((10, 66))
    a[2, 3] = 1e39  # finite in float64, inf in float32
    np.save(tmp_path / "big.npy", a)
    with pytest.raises(ValueError, match=r"big.npy: motion features holds 1e\+39 at index \[2, 3\], beyond float32"):
        load_feature_motion(str(tmp_path / "big.npy"), 66)
    np.save(tmp_path / "c.npy", np.zeros((10, 66), np.complex128))
    with pytest.raises(ValueError, match="c.npy: expected raw features"):
        load_feature_motion(str(tmp_path / "c.npy"), 66)
    np.save(tmp_path / "ok.npy", np.ones((10, 66)))
    ok = load_feature_motion(str(tmp_path / "ok.npy"), 66)
    assert ok.dtype == np.float32 and ok.shape == (10, 66)


def test_every_motion_reader_refuses_absurd_values_naming_file_and_index(tmp_path):
    """0.7.0 checked the magnitude of joint positions only: features scaled by 1e30 (finite in float32)
    were scored (`smdm eval --motions`) and trained on."""
    from helpers.synthetic_data import write_humanml3d
    from smdm_plugin.io.humanml3d import load_humanml3d

    a = np.ones((10, 66), np.float32)
    a[4, 2] = -3e30
    np.save(tmp_path / "m.npy", a)
    with pytest.raises(ValueError, match=r"m.npy: motion features reach 3e\+30 at index \[4, 2\] \(beyond ±1e\+07\)"):
        load_feature_motion(str(tmp_path / "m.npy"), 66)
    np.save(tmp_path / "ok.npy", np.full((10, 66), 9.9e6, np.float32))  # at the bound: a motion still
    assert load_feature_motion(str(tmp_path / "ok.npy"), 66).shape == (10, 66)
    data = write_humanml3d(tmp_path / "d")
    path = data / "new_joint_vecs" / "train002.npy"
    np.save(path, np.load(path) * np.float32(1e30))
    with pytest.raises(ValueError, match=rf"data: {path}: motion features reach .* at index \["):
        load_humanml3d(str(data), "train", 196, 20)
    path = data / "new_joints" / "val001.npy"
    np.save(path, np.load(path) * np.float32(1e30))
    with pytest.raises(ValueError, match=rf"data: {path}: joint positions reach .* at index \["):
        load_humanml3d(str(data), "val", 196, 20, joints=True)


def test_check_array_refuses_float64_beyond_float32():
    with pytest.raises(ValueError, match="beyond float32's range"):
        check_array(np.array([1.0, -4e38]), "x.npy")
    assert check_array(np.array([1.0, 3e38]), "x.npy").dtype == np.float64  # within range: unchanged


# ------------------------------------------------------------------------------ data by content
def test_file_digests_identify_data_by_content(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for root in (a, b):
        (root / "sub").mkdir(parents=True)
        (root / "sub" / "x.npy").write_bytes(b"1234")
        (root / "y.txt").write_bytes(b"y")
    da = file_digests(str(a), [str(a / "sub" / "x.npy"), str(a / "y.txt")])
    db = file_digests(str(b), [str(b / "sub" / "x.npy"), str(b / "y.txt")])
    assert da == db and digests_fingerprint(da) == digests_fingerprint(db)  # a copy elsewhere: the same data
    (b / "sub" / "x.npy").write_bytes(b"1235")  # same size, other content
    (b / "z.txt").write_bytes(b"z")
    db = file_digests(str(b), [str(b / "sub" / "x.npy"), str(b / "z.txt")])
    assert digests_fingerprint(da) != digests_fingerprint(db)
    assert describe_changes(da, db) == "changed: sub/x.npy; added: z.txt; removed: y.txt"


def test_other_readers_of_the_data_folder_name_the_file(tmp_path):
    """Joint files and captions of a HumanML3D-format folder: 0.4.0 raised EOFError /
    UnicodeDecodeError tracebacks."""
    from smdm_plugin.io.captions import read_captions
    from smdm_plugin.io.humanml3d import load_humanml3d
    from helpers.synthetic_data import write_humanml3d

    root = write_humanml3d(tmp_path / "d")
    bad = root / "new_joints" / "train001.npy"
    bad.write_bytes(b"")
    with pytest.raises(ValueError, match="train001.npy: not a readable .npy file"):
        load_humanml3d(str(root), "train", 64, 20, joints=True)
    (tmp_path / "c.txt").write_bytes(b"\xff\xfea man walks")
    with pytest.raises(ValueError, match="c.txt: not UTF-8 text"):
        read_captions(str(tmp_path / "c.txt"))
    (tmp_path / "ok.txt").write_bytes(b"\xef\xbb\xbfa man walks#a/DET man/NOUN walk/VERB#0.0#0.0\r\n\r\nhe runs\r")
    assert [c.text for c in read_captions(str(tmp_path / "ok.txt"))] == ["a man walks", "he runs"]
