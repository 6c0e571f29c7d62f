"""Every command's argument errors are one line: ``error: PROG: MESSAGE (see PROG --help)`` and exit code 2.

The commands are pyproject.toml's console scripts and the ``python -m`` tools; each one's parsers (its
subcommands' included) are found from the parser its ``main`` builds, not listed here.
"""

from __future__ import annotations

import argparse
import importlib
import os
import shutil
import subprocess
import sys
import tomllib

import pytest
from conftest import ROOT, refusal

from dssp_core.cli_runner import ArgumentParser

MODULE_TOOLS = {"python -m export.to_onnx": "export.to_onnx:main", "python -m export.verify": "export.verify:main"}
COMMANDS = {**tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"], **MODULE_TOOLS}
UNKNOWN = "--no-such-flag"


def entry(command: str):
    module, func = COMMANDS[command].split(":")
    return getattr(importlib.import_module(module), func)


class _Parsed(Exception):
    """Raised instead of parsing: the parser has been seen."""


def parser_of(main, argv: list[str]) -> argparse.ArgumentParser:
    """The parser ``main(argv)`` parses its arguments with (caught at its first parse, before it runs anything)."""
    seen = []
    original = argparse.ArgumentParser.parse_known_args

    def seen_instead(self, args=None, namespace=None):
        seen.append(self)
        raise _Parsed

    argparse.ArgumentParser.parse_known_args = seen_instead
    try:
        main(list(argv))
    except _Parsed:
        pass
    finally:
        argparse.ArgumentParser.parse_known_args = original
    assert seen, f"{argv} was never parsed"
    return seen[0]


def subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    return {
        name: sub
        for action in parser._actions
        if isinstance(action, argparse._SubParsersAction)
        for name, sub in action.choices.items()
    }


def parsers(command: str) -> list[tuple[list[str], argparse.ArgumentParser]]:
    """(subcommand words, parser) of every parser of ``command``: the top one and each subcommand's (a subcommand
    that hands its arguments to another command's parser, as ``dssp-sim record`` does, gives that parser)."""
    main = entry(command)
    top = parser_of(main, [])
    found = [([], top)]
    for name, sub in subparsers(top).items():
        own = parser_of(main, [name])
        found.append(([name], own if own.prog != top.prog else sub))
    return found


def required_args(parser: argparse.ArgumentParser) -> list[str]:
    """Values for every required argument of ``parser`` that its types accept (so only the flag added is wrong)."""

    def value(action) -> list[str]:
        convert = parser._registry_get("type", action.type, action.type)
        if action.choices:
            candidates = [str(next(iter(action.choices)))]
        else:
            candidates = ["1", "tap", "x"]
        for text in candidates:
            try:
                if callable(convert):
                    convert(text)
            except (ValueError, TypeError, argparse.ArgumentTypeError):
                continue
            return [text] * (action.nargs if isinstance(action.nargs, int) else 1)
        raise AssertionError(f"{parser.prog}: no value for {action.dest}")

    args = []
    chosen = {g._group_actions[0] for g in parser._mutually_exclusive_groups if g.required}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) or not (action.required or action in chosen):
            continue
        args += (
            (value(action) if not action.option_strings else [action.option_strings[0], *value(action)])
            if action.nargs != 0
            else [action.option_strings[0]]
        )
    return args


def outcome(main, argv: list[str], capsys) -> tuple[int, str, str]:
    """``main(argv)`` in-process: (exit code, stdout, stderr)."""
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def assert_one_line(command: str, argv: list[str], result: tuple[int, str, str], words: str) -> str:
    """The :func:`conftest.refusal` line of ``command argv`` (its ``result``) holds ``words`` and ends by pointing
    at ``--help``."""
    line = refusal(result, words)
    assert line.endswith(" --help)"), (f"{command} {' '.join(argv)}", line)
    return line


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_parser_is_the_one_line_parser(command):
    found = parsers(command)
    for words, parser in found:
        assert isinstance(parser, ArgumentParser), (command, words, type(parser))
        for name, sub in subparsers(parser).items():
            assert isinstance(sub, ArgumentParser), (command, words, name, type(sub))


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_an_unknown_flag_is_one_line(command, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    main = entry(command)
    leaves = [(words, p) for words, p in parsers(command) if not subparsers(p)]
    assert leaves
    for words, parser in leaves:
        argv = [*words, *required_args(parser), UNKNOWN]
        line = assert_one_line(command, argv, outcome(main, argv, capsys), f"unrecognized arguments: {UNKNOWN}")
        assert line.startswith(f"error: {parser.prog.split()[0]}"), line
    assert list(tmp_path.iterdir()) == []  # nothing ran


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_missing_required_argument_is_one_line(command, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    main = entry(command)
    cases = [(words, p) for words, p in parsers(command) if required_args(p) or subparsers(p)]
    assert cases, f"{command} has no required argument"
    for words, parser in cases:
        line = assert_one_line(command, words, outcome(main, list(words), capsys), "required")
        assert line.startswith(f"error: {parser.prog}: "), line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_the_installed_command_says_it_in_one_line(command, tmp_path):
    """The same through the console script (or ``python -m``), in a process of its own."""
    if command in MODULE_TOOLS:
        exe = [sys.executable, "-m", command.split()[-1]]
    else:
        path = shutil.which(command)
        assert path is not None, f"{command} is not installed (pip install -e .)"
        exe = [path]
    words, parser = next((w, p) for w, p in parsers(command) if not subparsers(p))
    argv = [*words, *required_args(parser), UNKNOWN]
    done = subprocess.run(
        [*exe, *argv],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert_one_line(command, argv, (done.returncode, done.stdout, done.stderr), f"unrecognized arguments: {UNKNOWN}")


def test_every_can_interface_flag_is_checked_when_parsed(tmp_path, capsys, monkeypatch):
    """Every parser with --interface takes python-can's interface names only (hardware.piper.bus.interface_name, or
    argparse's choices where a command takes a few):
    a name python-can lacks is one line before anything opens, not python-can's error when the bus opens."""
    monkeypatch.chdir(tmp_path)
    checked = []
    for command in sorted(COMMANDS):
        main = entry(command)
        for words, parser in parsers(command):
            action = parser._option_string_actions.get("--interface")
            if action is None or subparsers(parser):
                continue
            argv = [*words, *required_args(parser), "--interface", "bogus"]
            expected = "invalid choice: 'bogus'" if action.choices else "'bogus' is not a python-can interface"
            assert_one_line(command, argv, outcome(main, argv, capsys), expected)
            checked.append(f"{command} {' '.join(words)}".strip())
    assert {"dssp-run", "dssp-record", "dssp-replay", "dssp-calibrate", "dssp-sim record", "dssp-sim calibrate"} <= set(
        checked
    )
    assert list(tmp_path.iterdir()) == []
