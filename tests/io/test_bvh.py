"""BVH reader + forward kinematics, checked on synthetic files and against the CMU data."""
from __future__ import annotations

import csv
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from smdm_plugin.io.bvh import (CMU_TO_METRES, HUMANML22_FROM_CMU, BVHError, BVHWarning, bvh_joint_positions,
                                cmu_to_humanml22, load_cmu_clip, read_bvh)

from helpers.paths import SHARED as DATA
MOCAP, HML = DATA / "cmu-mocap", DATA / "cmu-humanml3d"

SIMPLE = """HIERARCHY
ROOT Hips
{
\tOFFSET 0 0 0
\tCHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
\tJOINT A
\t{
\t\tOFFSET 0 0 1
\t\tCHANNELS 3 Xrotation Yrotation Zrotation
\t\tJOINT B
\t\t{
\t\t\tOFFSET 0 0 1
\t\t\tCHANNELS 3 Yrotation Xrotation Zrotation
\t\t\tEnd Site
\t\t\t{
\t\t\t\tOFFSET 0 2 0
\t\t\t}
\t\t}
\t}
\tJOINT C
\t{
\t\tOFFSET 1 0 0
\t\tCHANNELS 3 Zrotation Yrotation Xrotation
\t}
}
MOTION
Frames: 3
Frame Time: 0.05
0 0 0 0 0 0 0 0 0 0 0 0 0 0 0
1 2 3 90 0 0 0 0 0 0 0 0 0 0 0
0 0 0 0 0 0 90 90 0 90 90 0 0 0 0
"""


def _write(tmp_path: Path, text: str, crlf: bool) -> Path:
    p = tmp_path / ("crlf.bvh" if crlf else "lf.bvh")
    p.write_bytes(text.replace("\n", "\r\n" if crlf else "\n").encode())
    return p


@pytest.mark.parametrize("crlf", [False, True])
def test_read_synthetic(tmp_path, crlf):
    b = read_bvh(_write(tmp_path, SIMPLE, crlf))
    assert b.names == ["Hips", "A", "B", "C"] and b.parents == [-1, 0, 1, 0]
    np.testing.assert_array_equal(b.offsets, [[0, 0, 0], [0, 0, 1], [0, 0, 1], [1, 0, 0]])
    assert b.channels[1] == ["Xrotation", "Yrotation", "Zrotation"] and len(b.channels[0]) == 6
    assert b.frame_time == 0.05 and b.motion.shape == (3, 15) and b.fps == pytest.approx(20)
    assert len(b.end_sites) == 1 and b.end_sites[0][0] == 2
    np.testing.assert_array_equal(b.end_sites[0][1], [0, 2, 0])


def test_fk_known_answers(tmp_path):
    p = bvh_joint_positions(read_bvh(_write(tmp_path, SIMPLE, False)))
    np.testing.assert_allclose(p[0], [[0, 0, 0], [0, 0, 1], [0, 0, 2], [1, 0, 0]], atol=1e-12)
    # frame 1: root at (1,2,3) turned 90° about Z: its +X child C moves to +Y
    np.testing.assert_allclose(p[1], [[1, 2, 3], [1, 2, 4], [1, 2, 5], [1, 3, 3]], atol=1e-12)
    # frame 2: A = Rx(90) Ry(90) (listed order) maps B's (0,0,1) to (1,0,0); B's own
    # Ry(90) Rx(90) does not move anything (no child joints), so B = A + (1,0,0)
    np.testing.assert_allclose(p[2, 2], [1, 0, 1], atol=1e-12)
    # and the order matters: with the reverse order (Ry Rx) the offset would go to (0,-1,0)
    swapped = read_bvh(_write(tmp_path, SIMPLE.replace(
        "CHANNELS 3 Xrotation Yrotation Zrotation", "CHANNELS 3 Yrotation Xrotation Zrotation"),
        False))
    np.testing.assert_allclose(bvh_joint_positions(swapped)[2, 2], [0, -1, 1], atol=1e-12)
    np.testing.assert_allclose(bvh_joint_positions(read_bvh(_write(tmp_path, SIMPLE, False)),
                                                   scale=2.0)[1, 3], [2, 6, 6], atol=1e-12)


def _scipy_fk(b, frames):
    from scipy.spatial.transform import Rotation
    out = np.zeros((len(frames), len(b.names), 3))
    Rg = [None] * len(b.names)
    col = 0
    for j, ch in enumerate(b.channels):
        vals = b.motion[frames, col:col + len(ch)]
        col += len(ch)
        rot = [(c[0], vals[:, k]) for k, c in enumerate(ch) if c.endswith("rotation")]
        tr = np.zeros((len(frames), 3))
        for k, c in enumerate(ch):
            if c.endswith("position"):
                tr[:, "XYZ".index(c[0])] = vals[:, k]
        R = Rotation.from_euler("".join(a for a, _ in rot), np.stack([v for _, v in rot], -1),
                                degrees=True)                         # upper case = intrinsic
        p = b.parents[j]
        if p < 0:
            out[:, j], Rg[j] = b.offsets[j] + tr, R
        else:
            out[:, j] = out[:, p] + Rg[p].apply(b.offsets[j] + tr)
            Rg[j] = Rg[p] * R
    return out


@pytest.mark.parametrize("name", ["variants/daz/85_02.bvh", "variants/3dsmax/131_01.bvh",
                                  "05_01.bvh"])
def test_fk_matches_scipy_on_mixed_channel_orders(name):
    path = MOCAP / name
    if not path.exists():
        pytest.skip("shared/data/cmu-mocap not available")
    b = read_bvh(path)
    frames = np.arange(0, b.num_frames, 37)
    np.testing.assert_allclose(bvh_joint_positions(b)[frames], _scipy_fk(b, frames), atol=1e-9)


def test_fk_matches_cmu_humanml3d_joints():
    """Pairwise joint distances (invariant to the stored heading rotation/translation) of our
    FK equal those of cmu-humanml3d/joints/<id>.npy for segments of several clips."""
    if not (HML / "index.csv").exists() or not MOCAP.exists():
        pytest.skip("shared/data not available")
    rows = [r for r in csv.DictReader(open(HML / "index.csv"))
            if r["clip"] in ("01_01", "05_02", "07_12", "16_58", "49_06")]
    assert rows
    clips = {}
    for r in rows:
        if r["clip"] not in clips:
            clips[r["clip"]] = load_cmu_clip(MOCAP / f"{r['clip']}.bvh")
        a = (int(r["first_file_frame"]) - 1) // 6
        b = (int(r["last_file_frame"]) - 1) // 6
        ours = clips[r["clip"]][a:b + 1]
        ref = np.load(HML / "joints" / f"{r['id']}.npy")
        assert ours.shape == ref.shape == (int(r["joint_frames"]), 22, 3)
        dist = lambda x: np.linalg.norm(x[:, :, None] - x[:, None], axis=-1)  # noqa: E731
        np.testing.assert_allclose(dist(ours), dist(ref), atol=1e-4)
        # the stored segment is ours turned about the vertical axis: heights relative to the
        # first frame's root height agree
        np.testing.assert_allclose(ours[..., 1] - ours[0, 0, 1], ref[..., 1] - ref[0, 0, 1],
                                   atol=1e-4)


def test_load_cmu_clip_frames_and_units():
    path = MOCAP / "16_58.bvh"
    if not path.exists():
        pytest.skip("shared/data/cmu-mocap not available")
    b = read_bvh(path)
    j = load_cmu_clip(path)
    assert j.shape == (len(range(1, b.num_frames, 6)), 22, 3)
    full = bvh_joint_positions(b, CMU_TO_METRES)
    np.testing.assert_allclose(j[1, 0], full[7, b.names.index("Hips")])
    assert 1.2 < j[0, 15, 1] - min(j[0, 10, 1], j[0, 11, 1]) < 1.6  # head above toes, metres


def test_cmu_to_humanml22_mapping_and_midpoints():
    names = sorted({n for e in HUMANML22_FROM_CMU for n in ((e,) if isinstance(e, str) else e)})
    names = ["Extra"] + names
    pos = np.random.default_rng(0).normal(size=(4, len(names), 3))
    out = cmu_to_humanml22(pos, names)
    at = lambda n: pos[:, names.index(n)]  # noqa: E731
    assert out.shape == (4, 22, 3)
    np.testing.assert_array_equal(out[:, 0], at("Hips"))
    np.testing.assert_array_equal(out[:, 12], at("Neck1"))
    np.testing.assert_array_equal(out[:, 21], at("RightHand"))
    np.testing.assert_allclose(out[:, 6], (at("Spine") + at("Spine1")) / 2)
    np.testing.assert_allclose(out[:, 13], (at("Spine1") + at("LeftArm")) / 2)
    np.testing.assert_allclose(out[:, 14], (at("Spine1") + at("RightArm")) / 2)
    with pytest.raises(ValueError, match=r"cmu_to_humanml22: names lack CMU joints \['Head'\]"):
        cmu_to_humanml22(np.delete(pos, names.index("Head"), 1),
                         [n for n in names if n != "Head"])
    with pytest.raises(ValueError, match=r"positions must be \[T, J=20, 3\], got \(4, 5, 3\)"):
        cmu_to_humanml22(pos[:, :5], names)


def test_joint_selection_features_are_root_relative():
    """BVH joints [.., T, 22, 3] -> the 64-D selection features (kind 'joints': joints 1..21 minus the root)."""
    from smdm_plugin.core.selection_features import extract_selection_features

    j = np.random.default_rng(1).normal(size=(2, 7, 22, 3))
    f = extract_selection_features(torch.from_numpy(j.reshape(2, 7, 66)), "joints", frame_index_scale=0.1).numpy()
    assert f.shape == (2, 7, 64)
    np.testing.assert_allclose(f[1, 3, :3], j[1, 3, 1] - j[1, 3, 0])
    np.testing.assert_allclose(f[1, 3, 60:63], j[1, 3, 21] - j[1, 3, 0])
    np.testing.assert_allclose(f[0, :, 63], np.arange(7) * 0.1)
    with pytest.raises(ValueError, match=r"kind='joints' needs x \[B, N, 3J\]"):
        extract_selection_features(torch.zeros(1, 7, 64), "joints")


@pytest.mark.parametrize("edit,match", [
    (lambda s: s.replace("0 0 0 0 0 0 90 90 0 90 90 0 0 0 0\n", ""), r"truncated motion: Frames: 3 declared, 2"),
    (lambda s: s.replace("\t}\n}\nMOTION", "\t}\nMOTION"), r"unbalanced braces"),
    (lambda s: s.replace("Yrotation Xrotation Zrotation", "Yrotation Wrotation Zrotation"),
     r"bad CHANNELS"),
    (lambda s: s.replace("Frames:", "Frame:"), r"line 26: MOTION needs 'Frames: n'"),
    (lambda s: s.replace("MOTION", "MOTIONLESS"), r"no MOTION section"),
    (lambda s: s.split("MOTION")[0], r"no MOTION section"),
])
def test_read_errors(tmp_path, edit, match):
    with pytest.raises(ValueError, match="read_bvh: .*" + match):
        read_bvh(_write(tmp_path, edit(SIMPLE), False))


# --------------------------------------------------------------------- tolerance and strictness
ROWS = SIMPLE.split("Frame Time: 0.05\n")[1].splitlines()


def _same(a, b):
    assert a.names == b.names and a.parents == b.parents and a.channels == b.channels
    assert a.frame_time == b.frame_time
    np.testing.assert_array_equal(a.offsets, b.offsets)
    np.testing.assert_array_equal(a.motion, b.motion)


@pytest.mark.parametrize("encode", [
    lambda s: b"\xef\xbb\xbf" + s.encode(),                                   # UTF-8 byte-order mark
    lambda s: ("\ufeff" + s.replace("\n", "\r\n")).encode(),                   # BOM + CRLF
    lambda s: s.replace("\n", "\r").encode(),                                  # old Mac CR
    lambda s: s.replace(" ", "\t").replace("\n", "\n\n").encode(),              # tabs, blank lines
    lambda s: s.replace("Frame Time: 0.05\n", "Frame Time:\t0.05  \n").encode() + b"\n   \n",
])
def test_tolerated_formatting_reads_the_same(tmp_path, encode):
    p = tmp_path / "x.bvh"
    p.write_bytes(encode(SIMPLE))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning for these
        _same(read_bvh(p), read_bvh(_write(tmp_path, SIMPLE, False)))


def test_latin1_joint_name(tmp_path):
    p = tmp_path / "x.bvh"
    p.write_bytes(SIMPLE.replace("JOINT C", "JOINT C\u00e9").encode("latin-1"))
    assert read_bvh(p).names[-1] == "C\u00e9"


def _boxing_toes_like(tmp_path):
    """Debian assimp-testmodels' Boxing_Toes.bvh declares 3069 frames and holds 3070 rows; the real
    file when installed, else one built the same way (declared n, n + 1 rows)."""
    real = Path("/usr/share/assimp/models/BVH/Boxing_Toes.bvh")
    if real.exists():
        return real, 3069
    rng = np.random.default_rng(0)
    rows = "\n".join(" ".join(f"{v:.4f}" for v in r) for r in rng.normal(size=(3070, 15)) * 30)
    p = tmp_path / "Boxing_Toes.bvh"
    p.write_text(SIMPLE.split("Frames: 3")[0] + "Frames: 3069\nFrame Time: 0.033333\n" + rows + "\n")
    return p, 3069


def test_one_extra_motion_row_is_ignored_with_a_warning(tmp_path):
    path, declared = _boxing_toes_like(tmp_path)
    with pytest.warns(BVHWarning, match=f"{path.name}: Frames: {declared} declared, {declared + 1} rows"):
        b = read_bvh(path)
    assert b.num_frames == declared
    # the rows kept are the file's first `declared` rows, in order
    lines = path.read_text().splitlines()
    first = next(k for k, ln in enumerate(lines) if ln.split()[:2] == ["Frame", "Time:"]) + 1
    body = [ln.split() for ln in lines[first:] if ln.strip()]
    np.testing.assert_array_equal(b.motion, np.array(body[:declared], dtype=float))
    # small file: the extra row is the one dropped
    p = tmp_path / "extra.bvh"
    p.write_text(SIMPLE + "9 9 9 9 9 9 9 9 9 9 9 9 9 9 9\n")
    with pytest.warns(BVHWarning, match=r"line 32\) is ignored"):
        _same(read_bvh(p), read_bvh(_write(tmp_path, SIMPLE, False)))


@pytest.mark.parametrize("edit,match,line", [
    (lambda s: s + "1 1 1 1 1 1 1 1 1 1 1 1 1 1 1\n" * 2, r"Frames: 3 declared, 5 motion rows present", None),
    (lambda s: s.replace("Frames: 3", "Frames: 4"), r"truncated motion: Frames: 4 declared, 3 row\(s\)", None),
    (lambda s: s.replace("Frame Time: 0.05", "Frame Time: 0"), r"Frame Time: must be .* > 0, got 0", 28),
    (lambda s: s.replace("Frame Time: 0.05", "Frame Time: -0.05"), r"Frame Time: must be", 28),
    (lambda s: s.replace("Frame Time: 0.05", "Frame Time: nan"), r"Frame Time: must be a finite", 28),
    (lambda s: s.replace("Frame Time: 0.05", "Frame Time: inf"), r"Frame Time: must be a finite", 28),
    (lambda s: s.replace("Frame Time: 0.05", "Frame Time: fast"), r"Frame Time: expected a number", 28),
    (lambda s: s.replace("Frames: 3", "Frames: three"), r"Frames: expected an integer, got 'three'", 27),
    (lambda s: s.replace("Frames: 3", "Frames: -1"), r"Frames: must be >= 0", 27),
    (lambda s: s.split("Frames: 3")[0] + "Frames: 0\nFrame Time: 0.05\n", r"Frames: 0: a motion needs at least 2", 27),
    (lambda s: s.split("Frames: 3")[0] + "Frames: 1\nFrame Time: 0.05\n" + "0 " * 15 + "\n",
     r"Frames: 1: a motion needs at least 2", 27),
    (lambda s: s.replace("Frame Time: 0.05", "Frame Time: 1e-320"), r"Frame Time: 1e-320 s is outside .* fps\)", 28),
    (lambda s: s.replace("Frame Time: 0.05", "Frame Time: 1e9"), r"Frame Time: 1e9 s is outside", 28),
    (lambda s: s.replace("1 2 3 90", "1 2 3e300 90"), r"motion value beyond", 30),
    (lambda s: s.replace("OFFSET 0 0 1\n\t\tCHANNELS 3 X", "OFFSET 0 1e30 1\n\t\tCHANNELS 3 X"), r"OFFSET: 1e30 is beyond", 8),
    (lambda s: s.replace("1 2 3 90", "1 2 x3 90"), r"motion value 'x3' is not a number", 30),
    (lambda s: s.replace("1 2 3 90", "1 2 nan 90"), r"not finite", 30),
    (lambda s: s.replace("1 2 3 90 0 0", "1 2 3 90 0"), r"motion row has 14 values, expected 15", 30),
    (lambda s: s.replace("1 2 3 90 0 0", "1 2 3 90 0 0 0"), r"motion row has 16 values, expected 15", 30),
    (lambda s: s.replace("OFFSET 0 0 1\n\t\tCHANNELS 3 X", "OFFSET 0 zero 1\n\t\tCHANNELS 3 X"),
     r"OFFSET: expected a number, got 'zero'", 8),
    (lambda s: s.replace("CHANNELS 3 Zrotation Yrotation Xrotation\n\t}", "CHANNELS 4 Zrotation Yrotation "
                         "Xrotation\n\t}"), r"bad CHANNELS 4", 23),
    (lambda s: s.replace("CHANNELS 3 Xrotation", "CHANNELS three Xrotation"), r"CHANNELS count: expected an integer", 9),
    (lambda s: s.replace("JOINT A", "JOINT"), r"unexpected token|without a name", None),
])
def test_strict_errors_name_the_file_and_line(tmp_path, edit, match, line):
    p = _write(tmp_path, edit(SIMPLE), False)
    with pytest.raises(BVHError, match=match) as e:
        read_bvh(p)
    assert isinstance(e.value, ValueError) and e.value.path == str(p)
    assert str(e.value).startswith(f"read_bvh: {p}")
    if line is not None:
        assert e.value.line == line and f"{p}, line {line}:" in str(e.value)


def test_folder_and_non_cmu_skeleton_are_clear_errors(tmp_path):
    with pytest.raises(BVHError, match="is a folder"):
        read_bvh(tmp_path)
    p = _write(tmp_path, SIMPLE, False)
    with pytest.raises(BVHError, match=rf"{p.name}: not a CMU skeleton: lacks the joints \['Head'"):
        load_cmu_clip(p)


def test_embedded_clips_are_the_bvh_clips_at_20_fps():
    """The package's own clips (smdm demo's default) equal a fresh conversion of their BVH files."""
    from smdm_plugin.io.bvh import load_cmu_clip
    from smdm_plugin.io.embedded import embedded_clips, embedded_descriptions

    clips = embedded_clips()
    assert len(clips) == 17 and all(j.shape[1:] == (22, 3) and j.dtype == np.float32 for _, j in clips)
    assert embedded_descriptions()["02_01"] == "walk"
    from helpers.paths import MOCAP as mocap
    if not mocap.exists():
        pytest.skip("../shared/data/cmu-mocap not available")
    for name, joints in clips[:3]:
        fresh = load_cmu_clip(mocap / f"{name}.bvh", fps=20)
        assert np.allclose(joints, fresh, atol=1e-5), name
