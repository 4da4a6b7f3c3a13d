"""``smdm render`` and the GIF writer: frame count read back with PIL, keyframes highlighted (found by
colour), every accepted input, clear errors, nothing overwritten."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from smdm_plugin.apps.common.animation import HIGHLIGHT, Panel, chains_from_parents, render_gif

HL = tuple(int(HIGHLIGHT[i:i + 2], 16) for i in (1, 3, 5))


def walk(n: int = 12) -> np.ndarray:
    """A 22-joint stick figure walking along +x: ``[n, 22, 3]`` metres, y up."""
    rng = np.random.default_rng(0)
    base = rng.normal(scale=0.25, size=(22, 3))
    base[:, 1] = np.abs(base[:, 1]) + 0.1
    base[0] = [0, 0.9, 0]
    t = np.arange(n)[:, None, None]
    return base[None] + t * np.array([0.05, 0, 0]) + 0.02 * np.sin(t + np.arange(22)[None, :, None])


def highlighted_pixels(gif: str) -> list:
    """Per GIF frame, the number of pixels of the highlight colour (within GIF palette rounding)."""
    im = Image.open(gif)
    counts = []
    for i in range(im.n_frames):
        im.seek(i)
        rgb = np.asarray(im.convert("RGB")).astype(int)
        counts.append(int((np.abs(rgb - np.array(HL)).max(-1) < 40).sum()))
    return counts


def test_gif_has_one_frame_per_motion_frame_and_highlights_keyframes(tmp_path):
    path = str(tmp_path / "a.gif")
    keys = [0, 5, 11]
    render_gif([Panel(walk(12), "a", keys), Panel(walk(9), "shorter", [2])], path, progress=False, panel_size=2)
    im = Image.open(path)
    assert im.n_frames == 12
    assert im.info["duration"] == 50  # 20 fps
    red = highlighted_pixels(path)
    for i, c in enumerate(red):
        if i in keys or i == 2:
            assert c > 30, (i, red)    # the figure is drawn red on its keyframes
        else:
            assert c == 0, (i, red)    # and red is used for nothing else
    # stride: every 3rd frame, same speed
    render_gif([Panel(walk(12), "a", keys)], str(tmp_path / "b.gif"), stride=3, progress=False, panel_size=2)
    im = Image.open(tmp_path / "b.gif")
    assert im.n_frames == 4 and im.info["duration"] == 150


def test_gif_is_not_overwritten_and_bad_input_is_clear(tmp_path):
    from smdm_plugin.io.files import OutputExistsError

    path = tmp_path / "a.gif"
    path.write_bytes(b"mine")
    with pytest.raises(OutputExistsError):
        render_gif([Panel(walk(3))], str(path), progress=False)
    assert path.read_bytes() == b"mine"
    render_gif([Panel(walk(3))], str(path), progress=False, overwrite=True, panel_size=2)
    assert Image.open(path).n_frames == 3
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary file left
    with pytest.raises(ValueError, match=r"keyframes must be in \[0, 3\)"):
        Panel(walk(3), keyframes=[3])
    with pytest.raises(ValueError, match="no skeleton known for J=7"):
        Panel(np.zeros((3, 7, 3)))
    with pytest.raises(ValueError, match=r"joints must be \[N, J, 3\]"):
        Panel(np.zeros((3, 22)))
    with pytest.raises(ValueError, match="must end in .gif"):
        render_gif([Panel(walk(3))], str(tmp_path / "a.mp4"), progress=False)


def test_chains_from_parents_cover_every_bone():
    parents = [-1, 0, 1, 2, 0, 4, 0, 6, 7, 7]
    chains = chains_from_parents(parents)
    bones = {(c[i], c[i + 1]) for c in chains for i in range(len(c) - 1)}
    assert bones == {(p, j) for j, p in enumerate(parents) if p >= 0}


def render(*args, cwd):
    return subprocess.run([sys.executable, "-m", "smdm_plugin", "render", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=600)


def test_render_command_on_every_input_kind(tmp_path, hml_dir, monkeypatch, capsys):
    from smdm_plugin.apps.render import main
    from smdm_plugin.io.representation import joints_to_joints66

    joints = np.load(hml_dir / "new_joints" / "000056.npy")[:10]
    np.save(tmp_path / "joints.npy", joints)
    np.save(tmp_path / "feats.npy", np.load(hml_dir / "new_joint_vecs" / "000056.npy")[:8])
    np.save(tmp_path / "j66.npy", joints_to_joints66(joints[:6]))
    np.save(tmp_path / "batch.npy", np.stack([joints, joints]))
    np.save(tmp_path / "results.npy", {"motion": joints.transpose(1, 2, 0)[None], "lengths": np.array([7])})
    # as a user runs it
    p = render("joints.npy", "feats.npy", "j66.npy", "--keyframes", "0", "4", "--titles", "a", "b", "c",
               "--size", "1.5", "--quiet", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    gif = tmp_path / "joints.gif"  # default name: the first input's, here
    assert Image.open(gif).n_frames == 10
    red = highlighted_pixels(str(gif))
    assert red[0] > 0 and red[4] > 0 and red[1] == red[2] == red[3] == 0
    before = gif.read_bytes()
    p = render("feats.npy", "--out", "joints.gif", cwd=tmp_path)
    assert p.returncode == 2 and "--overwrite" in p.stderr and "Traceback" not in p.stderr
    assert gif.read_bytes() == before
    # the rest in process (same entry point, faster)
    monkeypatch.chdir(tmp_path)
    assert main(["batch.npy", "--sample", "1", "--out", "b.gif", "--quiet", "--size", "1.5"]) == 0
    assert Image.open(tmp_path / "b.gif").n_frames == 10
    assert main(["results.npy", "--allow-pickle", "--out", "r.gif", "--quiet", "--size", "1.5"]) == 0
    assert Image.open(tmp_path / "r.gif").n_frames == 7
    np.save(tmp_path / "vector.npy", np.zeros(263))
    for args, msg in ((["results.npy"], "--allow-pickle"),
                      (["feats.npy", "--keyframes", "9"], "beyond the 8 frames"),
                      (["joints.npy", "--fps", "0"], "argument --fps"),
                      (["joints.npy", "--stride", "-1"], "argument --stride"),
                      (["joints.npy", "--titles", "x", "y"], "one title per motion"),
                      (["joints.npy", "--out", "x.png"], "must end in .gif"),
                      (["vector.npy"], "is not a motion"),
                      (["missing.npy"], "no such file")):
        with pytest.raises(SystemExit) as e:
            main([*args, "--out", "x.gif"] if "--out" not in args else args)
        err = capsys.readouterr().err
        assert e.value.code == 2 and msg in err, (args, err)
    assert not (tmp_path / "x.gif").exists()


def test_render_bvh(tmp_path, mocap_files):
    from smdm_plugin.apps.common.keyframe_study import find_bvh

    files = find_bvh([os.path.dirname(mocap_files[0])])
    if not files:
        pytest.skip("no BVH clip available")
    p = render(os.path.abspath(files[0]), "--stride", "40", "--out", "c.gif", "--no-progress", "--size", "1.5", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    n = int(p.stdout.split(": ")[1].split()[0])  # "<file>: N frames, 22 joints (bvh)"
    assert Image.open(tmp_path / "c.gif").n_frames == len(range(0, n, 40))


def two_joint_bvh(path, fps: float, frames: int = 30) -> str:
    """A BVH of a two-joint skeleton (not CMU's) recorded at ``fps``, swinging its end."""
    rows = "\n".join(f"0 90 0 0 0 0 0 0 {10 * np.sin(i / 3):.4f}" for i in range(frames))
    path.write_text("HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n  CHANNELS 6 Xposition Yposition Zposition "
                    "Zrotation Xrotation Yrotation\n  JOINT Chest\n  {\n    OFFSET 0 10 0\n    CHANNELS 3 Zrotation "
                    "Xrotation Yrotation\n    End Site\n    {\n      OFFSET 0 10 0\n    }\n  }\n}\nMOTION\n"
                    f"Frames: {frames}\nFrame Time: {1 / fps:.6f}\n{rows}\n")
    return str(path)


def test_a_bvh_plays_at_the_rate_it_has_and_says_so(tmp_path):
    """Frames of a BVH are only skipped: a file at 30 fps drawn for --fps 20 keeps every 2nd frame (15 fps), is
    timed at 15 fps and says so (0.10.6 timed it at the asked 20: too fast; --fps 240 of a 120 fps file played
    twice as fast); a rate the file gives exactly is timed at it, without a word."""
    from smdm_plugin.apps.common.motion_files import load_motion, rate_differs

    bvh = two_joint_bvh(tmp_path / "swing.bvh", 30.0)
    m = load_motion(bvh, fps=20)
    assert m.fps == 15 and len(m.joints) == 15 and "gives 15 fps, not 20" in rate_differs(m, 20)
    assert load_motion(bvh, fps=30).fps == 30 and rate_differs(load_motion(bvh, fps=30), 30) is None
    assert load_motion(bvh, fps=60).fps == 30           # never made up
    p = render(bvh, "--fps", "20", "--out", "s.gif", "--no-progress", "--size", "1", cwd=tmp_path)
    assert p.returncode == 0 and "warning: " in p.stderr and "gives 15 fps, not 20" in p.stderr, p.stderr
    assert Image.open(tmp_path / "s.gif").info["duration"] in (60, 70)    # 1000 / 15 ms, in GIF's 10 ms steps
    p = render(bvh, "--fps", "30", "--out", "t.gif", "--no-progress", "--size", "1", cwd=tmp_path)
    assert p.returncode == 0 and "warning" not in p.stderr, p.stderr
    assert Image.open(tmp_path / "t.gif").info["duration"] in (30, 40)
