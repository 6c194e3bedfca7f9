"""Command-line options generated from typed config dataclasses: one helper for every `rwm-gym` command, benchmark
and example, so a field's name, type, default and docstring are written once (in the dataclass)."""

from __future__ import annotations

import argparse
import ast
import inspect
import math
import numbers
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import MISSING, Field, dataclass, field, fields, replace
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
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    finite: bool = False,
):
    """A dataclass field with the command-line details its default and annotation cannot say, read by
    `add_dataclass_options`: `flags` in place of `--field-name` (e.g. `--in` for a field `where`), further `aliases`,
    the `parse` type, `choices`, `nargs`, `metavar`; `append`: the flag is repeatable, each value appended; `one_of`:
    a name shared by fields of which exactly one must be given (an argparse mutually exclusive group). A field with
    no default is a required flag.

    ge, gt, le, lt, finite: the field's `Range` (a number, or each number of a tuple, finite and >=, >, <=, < the
    bound), checked once for the API and the command line alike: `check_ranges(self)` in the dataclass's
    `__post_init__`, and the flag's parser (its error names the flag)."""
    cli = dict(flags=flags, aliases=aliases, type=parse, choices=choices, nargs=nargs, metavar=metavar)
    cli.update(action="append" if append else None, one_of=one_of)
    metadata: dict[str, object] = {"cli": {k: v for k, v in cli.items() if v}}
    if finite or any(b is not None for b in (ge, gt, le, lt)):
        metadata["range"] = Range(ge=ge, gt=gt, le=le, lt=lt)
    return field(default=default, default_factory=default_factory, metadata=metadata)  # type: ignore[arg-type]


@dataclass(frozen=True)
class Range:
    """The values a numeric field takes: finite, and within the bounds given (ge: >=, gt: >, le: <=, lt: <)."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None

    def __str__(self) -> str:
        bounds = ((">=", self.ge), (">", self.gt), ("<=", self.le), ("<", self.lt))
        return " and ".join(f"{op} {b:g}" for op, b in bounds if b is not None) or "a finite number"

    def admits(self, value: float) -> bool:
        """Whether the number `value` is finite and within the bounds."""
        return math.isfinite(value) and not (
            (self.ge is not None and value < self.ge)
            or (self.gt is not None and value <= self.gt)
            or (self.le is not None and value > self.le)
            or (self.lt is not None and value >= self.lt)
        )

    def check(self, name: str, value: object) -> None:
        """A one-line ValueError naming `name` unless `value` (a number, or each number of a sequence; None passes)
        is in range."""
        if value is None:
            return
        items = value if isinstance(value, Iterable) and not isinstance(value, str) else (value,)
        for item in items:
            real = isinstance(item, numbers.Real) and not isinstance(item, bool)
            if not (real and self.admits(float(item))):
                shown = list(value) if isinstance(value, tuple) else value
                raise ValueError(f"{name} must be {self}, got {shown!r}")


def field_range(f: Field) -> Range | None:
    """The `Range` a field's `option(ge=..., ...)` gives, or None."""
    return f.metadata.get("range")


def check_ranges(obj: object, label: str = "{cls}.{field}") -> None:
    """A one-line ValueError naming the first field of the dataclass `obj` whose value is outside its `Range` (as
    `label` words it): the one check a config's `__post_init__` makes, so the API refuses what the command line
    refuses."""
    for f in fields(obj):  # type: ignore[arg-type]
        if (rule := field_range(f)) is not None:
            rule.check(label.format(cls=type(obj).__name__, field=f.name), getattr(obj, f.name))


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
        cli.setdefault("type", _flag_type(cls, f.name, default, field_range(f)))
        if not cli.get("choices"):  # argparse's metavar, named after the flag rather than the dest
            cli.setdefault("metavar", names[0].lstrip("-").replace("-", "_").upper())
        value = list(value) if isinstance(value, tuple) else value  # argparse appends to (and prints) a list
        target.add_argument(*names, dest=f.name, default=value, help=help_text, required=is_required, **cli)


def _flag_type(cls: type, name: str, default: object, rule: Range | None = None) -> Callable[[str], object]:
    """The type a field's flag parses its text to: its default's, else (None, a tuple or no default) its
    annotation's, else the text itself. A number is checked against the field's range (a float: finite at least)."""
    if default is not None and default is not MISSING and not isinstance(default, tuple):
        kind = type(default)
    else:
        kind = _annotated_types(cls).get(name, str)
    return number(kind, rule) if kind in (int, float) else kind


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


def number(kind: type, rule: Range | None = None) -> Callable[[str], object]:
    """An argparse type: `kind` (int or float) parsed from the text, in `rule`'s range if given; an int may be written
    as an integral float ("64.0", "6.4e1"). Else a one-line error, which argparse prefixes with the flag."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            try:
                value = float(text)
            except ValueError:
                value = None
            if kind is not int or value is None or not value.is_integer():
                expected = "an integer" if kind is int else "a number"
                raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
            value = int(value)
        if not (rule or Range()).admits(float(value)):
            raise argparse.ArgumentTypeError(f"must be {rule or Range()}, got {text}")
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its "invalid ... value" message
    return parse


positive_int = number(int, Range(ge=1))
"""An argparse type for counts that must be at least 1."""
non_negative_int = number(int, Range(ge=0))
"""An argparse type for counts and budgets that may be 0."""
non_negative_float = number(float, Range(ge=0))
"""An argparse type for finite amounts >= 0 (minutes, noise std)."""


def torch_device(text: str) -> str:
    """An argparse type: a torch device this machine has ("cpu", "cuda", "cuda:1", "mps"), else a one-line error."""
    import torch

    try:
        device = torch.device(text)
    except (RuntimeError, ValueError):
        raise argparse.ArgumentTypeError(f"{text!r} is not a torch device (cpu, cuda, cuda:N, mps)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise argparse.ArgumentTypeError(f"{text}: torch finds no CUDA GPU on this machine (use cpu)")
    if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
        raise argparse.ArgumentTypeError(f"{text}: this machine has {torch.cuda.device_count()} CUDA GPU(s)")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise argparse.ArgumentTypeError(f"{text}: torch finds no MPS device on this machine (use cpu)")
    return text
