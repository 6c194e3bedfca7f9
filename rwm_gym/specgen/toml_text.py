"""Write a spec's tables as TOML text with comments (the generated specs are read and edited by people).

Hand-written rather than `tomli-w` because that writer puts every array element on its own line (a 24-column state
group would take 72 lines) and cannot write comments; `write_spec_text` output is checked by parsing it back.
"""

from __future__ import annotations

import json
import math


def value_text(value) -> str:
    """One TOML value: strings, bools, ints, floats (`inf` allowed), lists of those, inline tables."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        if math.isnan(value):
            raise ValueError("NaN has no place in a task spec")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # a JSON string is a valid TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(value_text(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {value_text(v)}" for k, v in value.items()) + " }"
    raise TypeError(f"cannot write {type(value).__name__} as TOML")


def table_text(name: str, table: dict, comments: dict[str, str] | None = None, *, array: bool = False) -> str:
    """`[name]` (or `[[name]]`) and its keys, each with an optional trailing comment."""
    comments = comments or {}
    lines = [f"[[{name}]]" if array else f"[{name}]"]
    for key, value in table.items():
        note = f"    # {comments[key]}" if key in comments else ""
        lines.append(f"{key} = {value_text(value)}{note}")
    return "\n".join(lines)


def significant(x: float, digits: int = 4) -> float:
    """x rounded to `digits` significant digits (how the shipped specs write normalisation figures)."""
    return float(f"{x:.{digits}g}")
