"""MkDocs hooks: the command-line reference is generated from the `rwm-gym` argparse parsers, and the API reference
names objects by their public `rwm_gym.NAME`, resolved here through `rwm_gym.EXPORTS` to the module that defines them.

`<!-- rwm-gym-cli -->` in a page becomes one section per subcommand with its `--help`; a line `::: rwm_gym.NAME`
becomes `::: <defining module>.NAME` for mkdocstrings. So neither page repeats what the code says.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

# this checkout's package, not another installed copy
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

CLI_MARK = "<!-- rwm-gym-cli -->"
API_LINE = re.compile(r"^::: rwm_gym\.(\w+)$", re.MULTILINE)


def cli_reference() -> str:
    os.environ.setdefault("COLUMNS", "110")  # argparse wraps help at the terminal width
    from rwm_gym.cli import COMMANDS, build_parser

    sections = []
    for name, (_, summary) in COMMANDS.items():
        parser = build_parser(name)
        sub = next(a for a in parser._actions if a.dest == "command").choices[name]  # argparse keeps no public map
        sub.prog = f"rwm-gym {name}"
        sections.append(
            f"## `rwm-gym {name}`\n\n{summary[0].upper()}{summary[1:]}.\n\n```text\n{sub.format_help()}```\n"
        )
    return "\n".join(sections)


def public_target(match: re.Match) -> str:
    from rwm_gym import EXPORTS

    name = match.group(1)
    if name not in EXPORTS:
        raise ValueError(f"::: rwm_gym.{name}: not in rwm_gym.EXPORTS")
    return f"::: {EXPORTS[name]}.{name}"


def on_page_markdown(markdown: str, page, config, files) -> str:
    if CLI_MARK in markdown:
        markdown = markdown.replace(CLI_MARK, cli_reference())
    return API_LINE.sub(public_target, markdown)
