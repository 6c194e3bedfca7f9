"""Command-line options generated from typed config dataclasses: one helper for every `rwm-gym` command, benchmark
and example, so a field's name, type, default and docstring are written once (in the dataclass)."""

from __future__ import annotations

import argparse
import ast
import inspect
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import MISSING, Field, field, fields, replace
from functools import cache
from pathlib import Path
from typing import get_args, get_origin, get_type_hints


@cache
def field_docs(cls: type) -> dict[str, str]:
    """The docstring under each field of a dataclass (read from its source), for `--help` texts."""
    docs, previous = {}, None
    for node in ast.parse(inspect.getsource(cls)).body[0].body:
        if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            previous = node.target.id
        elif previous and isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            docs[previous] = " ".join(str(node.value.value).split())
            previous = None
        else:
            previous = None
    return docs


def option(
    default: object = MISSING,
    *,
    default_factory: Callable[[], object] | object = MISSING,
    flags: Sequence[str] = (),
    aliases: Sequence[str] = (),
    parse: Callable[[str], object] | None = None,
    choices: Sequence[object] | None = None,
    nargs: str | None = None,
    metavar: str | None = None,
    append: bool = False,
    one_of: str | None = None,
):
    """A dataclass field with the command-line details its default and annotation cannot say, read by
    `add_dataclass_options`: `flags` in place of `--field-name` (e.g. `--in` for a field `where`), further `aliases`,
    the `parse` type, `choices`, `nargs`, `metavar`; `append`: the flag is repeatable, each value appended; `one_of`:
    a name shared by fields of which exactly one must be given (an argparse mutually exclusive group). A field with
    no default is a required flag."""
    cli = dict(flags=flags, aliases=aliases, type=parse, choices=choices, nargs=nargs, metavar=metavar)
    cli.update(action="append" if append else None, one_of=one_of)
    metadata = {"cli": {k: v for k, v in cli.items() if v}}
    return field(default=default, default_factory=default_factory, metadata=metadata)  # type: ignore[arg-type]


_PARSED_TYPES = (int, float, Path)
"""Annotated types a flag parses its text to (anything else stays the text)."""


@cache
def _annotated_types(cls: type) -> dict[str, type]:
    """Each field's annotated type where it is one of `_PARSED_TYPES`, read through `X | None` and `tuple[X, ...]`
    (a flag parses one value at a time)."""
    try:
        hints = get_type_hints(cls)
    except (NameError, TypeError):  # an annotation naming what only a type checker imports
        return {}
    found = {}
    for name, hint in hints.items():
        while get_origin(hint) is not None:  # tuple[Path, ...] | None: Path
            args = [a for a in get_args(hint) if a is not type(None) and a is not Ellipsis]
            if len(args) != 1:
                break
            hint = args[0]
        if hint in _PARSED_TYPES:
            found[name] = hint
    return found


def _field_default(f: Field, defaults: object | None) -> object:
    """A field's default (from `defaults` if given), MISSING for a required one."""
    if defaults is not None:
        return getattr(defaults, f.name)
    if f.default_factory is not MISSING:
        return f.default_factory()
    return f.default


def _help(doc: str, default: object) -> str:
    """The field docstring, with the default named unless the docstring names it ("(default ..." or "default: ...")
    or there is none (a required flag)."""
    shown = list(default) if isinstance(default, tuple) else default
    named = default is MISSING or re.search(r"\(default\b|\bdefault:", doc) is not None
    return (doc if named else f"{doc} (default {shown})").strip().replace("%", "%%")


def add_dataclass_options(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    cls: type,
    *,
    types: Mapping[str, Callable[[str], object]] | None = None,
    choices: Mapping[str, Sequence[object]] | None = None,
    nargs: Mapping[str, str] | None = None,
    skip: Iterable[str] = (),
    defaults_none: bool = False,
    defaults: object | None = None,
    aliases: Mapping[str, Sequence[str]] | None = None,
    flags: Mapping[str, Sequence[str]] | None = None,
    required: Iterable[str] = (),
) -> None:
    """One `--field-name` option per field of the dataclass `cls`: its type (booleans as `--x/--no-x`; else the
    type `types` or the field's `option(parse=)` gives, else its default's, else its annotation's: int, float or
    Path), its field docstring and default as the help text. A field's `option` metadata gives its flags, choices,
    nargs and mutually exclusive group; the keyword mappings here give the same for a class that carries none.

    defaults_none: every option defaults to None (the help still names the field's default), so a caller can tell
    the options given from those left out, e.g. to override only those on a resumed run.
    defaults: an instance of `cls` whose values are the defaults (e.g. a nested config's own default), else the
    fields' defaults. aliases: further flags of a field (e.g. a name users knew before the field moved); flags: the
    flags in place of `--field-name`. required: fields whose flag must be given though they have a default.
    """
    docs, skip, required = field_docs(cls), set(skip), set(required)
    given = {"type": types, "choices": choices, "nargs": nargs, "flags": flags}
    exclusive: dict[str, argparse._MutuallyExclusiveGroup] = {}
    for f in fields(cls):
        if f.name in skip:
            continue
        default = _field_default(f, defaults)
        cli = {**f.metadata.get("cli", {}), **{k: v[f.name] for k, v in given.items() if f.name in (v or {})}}
        names = [*cli.pop("flags", ["--" + f.name.replace("_", "-")]), *cli.pop("aliases", ())]
        names += (aliases or {}).get(f.name, ())
        target = parser
        if group := cli.pop("one_of", None):
            if group not in exclusive:
                exclusive[group] = parser.add_mutually_exclusive_group(required=True)
            target = exclusive[group]
        help_text = _help(docs.get(f.name, ""), default)
        value = None if defaults_none or default is MISSING else default
        is_required = default is MISSING or f.name in required
        if isinstance(default, bool):
            action = argparse.BooleanOptionalAction
            target.add_argument(*names, dest=f.name, action=action, default=value, help=help_text, required=is_required)
            continue
        cli.setdefault("type", _flag_type(cls, f.name, default))
        if not cli.get("choices"):  # argparse's metavar, named after the flag rather than the dest
            cli.setdefault("metavar", names[0].lstrip("-").replace("-", "_").upper())
        value = list(value) if isinstance(value, tuple) else value  # argparse appends to (and prints) a list
        target.add_argument(*names, dest=f.name, default=value, help=help_text, required=is_required, **cli)


def _flag_type(cls: type, name: str, default: object) -> Callable[[str], object]:
    """The type a field's flag parses its text to: its default's, else (None, a tuple or no default) its
    annotation's, else the text itself."""
    if default is not None and default is not MISSING and not isinstance(default, tuple):
        return type(default)
    return _annotated_types(cls).get(name, str)


def dataclass_from_args(
    cls: type, args: argparse.Namespace, *, skip: Iterable[str] = (), base: object | None = None, **nested
):
    """`cls` built from the options `add_dataclass_options` added: lists become tuples; a field left out of `args`
    (skipped) or None there (`defaults_none`) keeps `base`'s value, else its default; `nested` gives the values of
    fields skipped because they hold another dataclass."""
    skip, given = set(skip), dict(nested)
    for f in fields(cls):
        if f.name in skip or f.name in given or not hasattr(args, f.name):
            continue
        value = getattr(args, f.name)
        if value is not None:
            given[f.name] = tuple(value) if isinstance(value, list) else value
    return replace(base, **given) if base is not None else cls(**given)


def parse_dataclass_args(cls: type, argv: Sequence[str] | None = None, **options):
    """`cls` built from the command line (`argv`, default sys.argv): a script's whole parser when its options are
    one dataclass, with its docstring as the description; `options` go to `add_dataclass_options`."""
    parser = argparse.ArgumentParser(description=cls.__doc__)
    add_dataclass_options(parser, cls, **options)
    return dataclass_from_args(cls, parser.parse_args(argv))


def _number(kind: type, low: float, strict: bool) -> Callable[[str], object]:
    """An argparse type: `kind` parsed from the text, finite and >= `low` (> `low` if strict); else a one-line error."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if value != value or value in (float("inf"), float("-inf")) or value < low or (strict and value == low):
            raise argparse.ArgumentTypeError(f"must be {'>' if strict else '>='} {low:g}, got {text}")
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its "invalid ... value" message
    return parse


positive_int = _number(int, 0, strict=True)
"""An argparse type for counts that must be at least 1."""
non_negative_int = _number(int, 0, strict=False)
"""An argparse type for counts and budgets that may be 0."""
non_negative_float = _number(float, 0.0, strict=False)
"""An argparse type for finite amounts >= 0 (minutes, noise std)."""
