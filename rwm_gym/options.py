"""Command-line options generated from typed config dataclasses: one helper for every `rwm-gym` command, benchmark
and example, so a field's name, type, default and docstring are written once (in the dataclass)."""

from __future__ import annotations

import argparse
import ast
import inspect
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import MISSING, fields, replace
from functools import cache


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
) -> None:
    """One `--field-name` option per field of the dataclass `cls`: its type (booleans as `--x/--no-x`; `types` for
    fields whose default does not say it, e.g. None), its field docstring and default as the help text.

    defaults_none: every option defaults to None (the help still names the field's default), so a caller can tell
    the options given from those left out, e.g. to override only those on a resumed run.
    defaults: an instance of `cls` whose values are the defaults (e.g. a nested config's own default), else the
    fields' defaults. aliases: further flags of a field (e.g. a name users knew before the field moved).
    """
    docs, skip = field_docs(cls), set(skip)
    for f in fields(cls):
        if f.name in skip:
            continue
        if defaults is not None:
            default = getattr(defaults, f.name)
        else:
            default = f.default if f.default is not MISSING else f.default_factory()  # type: ignore[misc]
        flags = ["--" + f.name.replace("_", "-"), *(aliases or {}).get(f.name, ())]
        shown = list(default) if isinstance(default, tuple) else default
        help_text = f"{docs.get(f.name, '')} (default {shown})".strip().replace("%", "%%")
        value = None if defaults_none else default
        if isinstance(default, bool):
            parser.add_argument(
                *flags, dest=f.name, action=argparse.BooleanOptionalAction, default=value, help=help_text
            )
            continue
        kind = (types or {}).get(f.name, type(default) if default is not None else str)
        parser.add_argument(
            *flags,
            dest=f.name,
            type=kind,
            default=value,
            help=help_text,
            choices=(choices or {}).get(f.name),
            nargs=(nargs or {}).get(f.name),
        )


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
    return cls(**vars(parser.parse_args(argv)))


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
