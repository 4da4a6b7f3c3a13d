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


# ------------------------------------------------------------------------------ the common flags
from smdm_plugin.apps.common.args import COMMON_FLAGS, add_common_flags, note_printer, progress_of  # noqa: E402

#: commands that take none of the common flags, and why (every other command takes all four)
NO_COMMON_FLAGS = {"run": "its arguments belong to the upstream command it runs",
                   "clips": "it lists or copies embedded clips: no computation"}
COMMON_ARGVS = [(c, a) for c, a in HELP_ARGVS if c not in NO_COMMON_FLAGS] + [
    ("ablate", ["--config", "quality_compute", "--help"])]  # the study's own parser


def leaf_parsers(cmd: str, argv: List[str]) -> List[argparse.ArgumentParser]:
    """The parsers a command really parses its options with: named ``smdm ...`` (not a pre-parser
    that only peeks at one option), without sub-commands (not a help-only parser of them)."""
    return [p for p in parsers_of(cmd, argv) if p.prog.startswith("smdm")
            and not any(isinstance(a, argparse._SubParsersAction) for a in p._actions)]


@pytest.mark.parametrize("cmd,argv", COMMON_ARGVS, ids=[" ".join([c] + a[:-1]) for c, a in COMMON_ARGVS])
def test_every_command_takes_the_common_flags(cmd: str, argv: List[str]) -> None:
    """--device, --threads, --no-progress, --quiet: each parser offers the flag (with its help) or
    refuses it with a reason (a hidden option that errors): never an 'unrecognized arguments'."""
    parsers = leaf_parsers(cmd, argv)
    assert parsers
    for p in parsers:
        missing = [f for f in COMMON_FLAGS if f not in p._option_string_actions]
        assert not missing, f"{p.prog} lacks {missing}"
    assert set(NO_COMMON_FLAGS) < set(COMMANDS)


def test_eval_has_no_progress() -> None:
    (p,) = leaf_parsers("eval", ["--help"])
    assert p._option_string_actions["--no-progress"].help != argparse.SUPPRESS


def test_no_command_calls_a_flag_a_no_op() -> None:
    """No help says a flag is only 'accepted for compatibility'."""
    for cmd, argv in COMMON_ARGVS:
        for p in leaf_parsers(cmd, argv):
            for a in p._actions:
                assert "compatibility" not in (a.help or ""), f"{p.prog} {a.option_strings}: {a.help}"


@pytest.mark.parametrize("cmd,argv,flag,why", [
    ("render", ["--device", "cpu", "m.npy"], "--device", "matplotlib"),
    ("render", ["--threads", "2", "m.npy"], "--threads", "matplotlib"),
    ("keyframes", ["--no-progress"], "--no-progress", "shows no progress"),
    ("bench", ["keyframes", "--quiet"], "--quiet", "prints only its result"),
    ("evaluator", ["check", "--no-progress", "x"], "--no-progress", "shows no progress"),
])
def test_a_flag_that_cannot_apply_is_refused_with_its_reason(cmd, argv, flag, why, capsys) -> None:
    with pytest.raises(SystemExit) as e:
        entry_point(cmd)(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {flag}: does not apply to smdm {cmd}" in err and why in err, err


def test_common_flags_mean_one_thing() -> None:
    p = argparse.ArgumentParser(prog="x")
    add_common_flags(p, device="cpu", threads_default=1)
    a = p.parse_args([])
    assert (a.device, a.threads, progress_of(a)) == ("cpu", 1, True) and note_printer(a) is print
    a = p.parse_args(["--no-progress", "--threads", "3"])
    assert a.threads == 3 and not progress_of(a) and note_printer(a) is print  # notes stay
    a = p.parse_args(["--quiet"])
    assert not progress_of(a) and note_printer(a) is not print  # --quiet: no progress, no notes
    with pytest.raises(SystemExit):
        p.parse_args(["--threads", "0"])
    q = argparse.ArgumentParser(prog="y")
    add_common_flags(q, device=None, threads=False, progress=False, quiet=False, why_not="nothing to run")
    assert q.parse_args([]).device is None
    for flag in (["--device", "cpu"], ["--threads", "2"], ["--no-progress"], ["--quiet"]):
        with pytest.raises(SystemExit):
            q.parse_args(flag)


def test_quiet_silences_the_notes_not_the_result(tmp_path) -> None:
    """smdm keyframes --quiet: the table (the result) prints, the notes on stderr do not."""
    import subprocess
    import sys

    def run(*flags):
        return subprocess.run([sys.executable, "-m", "smdm_plugin", "keyframes", "--reductions", "0.8",
                               "--threads", "1", *flags], capture_output=True, text=True, cwd=tmp_path,
                              env={**__import__("os").environ, "SMDM_MOCAP": ""})
    loud, quiet = run(), run("--quiet")
    assert loud.returncode == quiet.returncode == 0, loud.stderr + quiet.stderr
    assert "motion from" in loud.stderr and "motion from" not in quiet.stderr
    assert "| method |" in quiet.stdout and quiet.stdout == loud.stdout
