"""Progress bars show only where they redraw in place: asked for (no ``--no-progress`` / ``--quiet``)
and stderr a terminal, unless ``--progress``; a log file of a command holds no bar redraws."""
from __future__ import annotations

import argparse
import io

import pytest

from helpers.commands import TINY_TRAIN
from smdm_plugin.apps import train as train_cli
from smdm_plugin.apps.common.args import add_common_flags, progress_of
from smdm_plugin.support.progress import ALWAYS, bars_on


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


class _Closed:
    def isatty(self) -> bool:
        raise ValueError("I/O operation on closed file")


def test_bars_show_on_a_terminal_only_unless_forced():
    assert bars_on(True, _Terminal()) and not bars_on(True, io.StringIO())
    assert not bars_on(True, object()) and not bars_on(True, _Closed())   # no isatty / closed: off
    assert bars_on(ALWAYS, io.StringIO()) and not bars_on(False, _Terminal())


def test_the_flags_give_the_decision():
    p = argparse.ArgumentParser(prog="x")
    add_common_flags(p, device="cpu", threads_default=1)
    assert progress_of(p.parse_args([])) is True                          # the terminal decides
    assert progress_of(p.parse_args(["--progress"])) == ALWAYS
    assert progress_of(p.parse_args(["--no-progress"])) is False and progress_of(p.parse_args(["--quiet"])) is False
    for both in (["--progress", "--no-progress"], ["--progress", "--quiet"], ["--quiet", "--progress"]):
        with pytest.raises(SystemExit):                                     # one of the two would be dropped
            p.parse_args(both)


def test_a_command_writing_to_a_file_shows_no_bar(synthetic_hml, tmp_path, capsys):
    tiny = [a for a in TINY_TRAIN if a != "--no-progress"]
    argv = ["--steps", "2", *tiny[tiny.index("--latent-dim"):]]
    base = ["--data", str(synthetic_hml), "--min-frames", "20", *argv]
    assert train_cli.main([*base, "--out", str(tmp_path / "a")]) == 0       # stderr captured: not a terminal
    err = capsys.readouterr().err
    assert "\r" not in err and "step/s" not in err, err
    assert train_cli.main([*base, "--out", str(tmp_path / "b"), "--progress"]) == 0
    assert "\r" in capsys.readouterr().err                                # forced: the bar redraws
