"""Every option of every ``smdm`` command has a help line (the parsers are the ones the commands
really use: captured while each command answers ``--help``), and a command's errors name it."""
from __future__ import annotations

import argparse
import contextlib
import io
from typing import List, Tuple

import pytest

from smdm_plugin.apps.cli import COMMANDS, entry_point

# argv that reaches each parser of a command: the command itself, and its sub-commands
HELP_ARGVS = [(cmd, ["--help"]) for cmd in COMMANDS] + [("bench", ["keyframes", "--help"])]


def parsers_of(cmd: str, argv: List[str]) -> List[argparse.ArgumentParser]:
    """The parsers ``smdm cmd argv`` parses with (sub-parsers included)."""
    seen: List[argparse.ArgumentParser] = []
    original = argparse.ArgumentParser.parse_known_args

    def spy(self, *args, **kwargs):
        seen.append(self)
        return original(self, *args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(argparse.ArgumentParser, "parse_known_args", spy)
        with contextlib.redirect_stdout(io.StringIO()), pytest.raises(SystemExit):
            entry_point(cmd)(argv)
    out, todo = [], list(seen)
    while todo:
        p = todo.pop()
        if p in out:
            continue
        out.append(p)
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                todo += list(a.choices.values())
    return out


def missing_help(p: argparse.ArgumentParser) -> List[str]:
    bad = []
    for a in p._actions:
        if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)) or a.help == argparse.SUPPRESS:
            continue
        if not (a.help or "").strip():
            bad.append("/".join(a.option_strings) or a.dest)
    return bad


@pytest.mark.parametrize("cmd,argv", HELP_ARGVS, ids=[" ".join([c] + a[:-1]) for c, a in HELP_ARGVS])
def test_every_option_has_help(cmd: str, argv: List[str]) -> None:
    parsers = parsers_of(cmd, argv)
    assert parsers, f"smdm {cmd}: no argparse parser seen"
    bad: List[Tuple[str, List[str]]] = [(p.prog, missing_help(p)) for p in parsers if missing_help(p)]
    assert not bad, f"options without help: {bad}"


def test_help_names_defaults_of_numeric_options() -> None:
    """A numeric option with a default says it in its help (``default`` or ``%(default)s``)."""
    bad = []
    for cmd, argv in HELP_ARGVS:
        for p in parsers_of(cmd, argv):
            for a in p._actions:
                if (a.option_strings and isinstance(a.default, (int, float)) and not isinstance(a.default, bool)
                        and a.help not in (None, argparse.SUPPRESS) and "default" not in a.help
                        and a.nargs in (None, "?")):
                    bad.append(f"{p.prog} {a.option_strings[0]}")
    assert not bad, f"numeric options whose help does not give the default: {bad}"


def test_spy_sees_an_option_without_help() -> None:
    """The check itself: a parser with a help-less option is reported."""
    p = argparse.ArgumentParser(prog="x")
    p.add_argument("--a", help="fine")
    p.add_argument("--b")
    assert missing_help(p) == ["--b"]


@pytest.mark.parametrize("cmd", ["keyframes", "inbetween", "render", "clips"])
def test_error_of_a_command_names_it(cmd: str, tmp_path, monkeypatch, capsys) -> None:
    """A command given nothing (or a bad file) talks about itself, not about another command."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("SMDM_MOCAP", raising=False)
    argv = {"keyframes": [str(tmp_path)], "inbetween": [], "render": [], "clips": ["export", "nope"]}[cmd]
    try:
        code = entry_point(cmd)(argv)
    except SystemExit as e:  # argparse's error()
        code = e.code
    assert code == 2
    err = capsys.readouterr().err
    assert f"smdm {cmd}" in err and "smdm demo:" not in err, err
