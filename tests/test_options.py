"""Command-line options generated from dataclasses (`rwm_gym.options`): every flag of every `rwm-gym` subcommand
comes from a field of one of the dataclasses its module lists in `OPTIONS`, so none is written by hand beside them."""

from __future__ import annotations

import argparse
import importlib
from dataclasses import dataclass, fields
from pathlib import Path

import pytest

from rwm_gym.cli import COMMANDS, build_parser
from rwm_gym.options import add_dataclass_options, dataclass_from_args, field_docs, option


def _subparser(command: str) -> argparse.ArgumentParser:
    parser = build_parser(command)
    return parser._subparsers._group_actions[0].choices[command]  # argparse keeps no public map


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_flag_is_a_field_of_the_commands_dataclasses(command):
    sub = _subparser(command)
    if sub.get_default("_missing"):
        pytest.skip(f"{command} is not available in this build")
    classes = importlib.import_module(COMMANDS[command][0]).OPTIONS
    docs = {f.name: field_docs(cls).get(f.name, "") for cls in classes for f in fields(cls)}
    for action in sub._actions:
        if isinstance(action, argparse._HelpAction):
            continue  # argparse's own --help
        flag = "/".join(action.option_strings) or action.dest
        assert action.dest in docs, f"rwm-gym {command} {flag}: not a field of {[c.__name__ for c in classes]}"
        assert (action.help or "").replace("%%", "%").startswith(docs[action.dest]), f"{command} {flag}: help"


@dataclass(frozen=True, kw_only=True)
class _Example:
    """An example."""

    out: Path
    """file to write"""
    where: str = option("a", flags=["--in"], choices=("a", "b"))
    """where it runs"""
    tags: tuple[str, ...] = option((), append=True)
    """tags (repeatable)"""
    sizes: tuple[int, ...] = option((1, 2), nargs="+")
    """sizes"""
    count: int | None = None
    """a count (default: none)"""
    left: str | None = option(None, one_of="side")
    right: str | None = option(None, one_of="side")
    fast: bool = False


def test_option_metadata_gives_flags_types_and_groups():
    parser = argparse.ArgumentParser()
    add_dataclass_options(parser, _Example)
    given = ["--out", "x", "--in", "b", "--tags", "t", "--tags", "u", "--sizes", "3", "--count", "4", "--left", "l"]
    options = dataclass_from_args(_Example, parser.parse_args(given))
    assert options == _Example(out=Path("x"), where="b", tags=("t", "u"), sizes=(3,), count=4, left="l")
    assert dataclass_from_args(_Example, parser.parse_args(["--out", "x", "--right", "r"])).sizes == (1, 2)
    for wrong in (["--left", "l"], ["--out", "x"], ["--out", "x", "--left", "l", "--right", "r"], ["--in", "c"]):
        with pytest.raises(SystemExit):
            parser.parse_args(wrong)  # no --out, neither side, both sides, a choice not offered
    text = " ".join(parser.format_help().split())
    assert "a count (default: none) --left" in text and "file to write --in" in text and "(default [1, 2])" in text
