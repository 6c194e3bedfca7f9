"""The README and the docs site: short, built without warnings, naming the public API, and written for users (no
log of past work)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import rwm_gym
from rwm_gym.cli import COMMANDS

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
USER_TEXT = [
    README,
    ROOT / "CHANGELOG.md",
    *sorted((ROOT / "docs").rglob("*.md")),
    *sorted((ROOT / "benchmarks").glob("*.md")),
]
CODE_TEXT = sorted((ROOT / "rwm_gym").rglob("*.py"))

# narration of past work: numbered work periods, tracker numbers, run letters and wall-clock times of day
ORDINALS = (
    "first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth|thirteenth|fourteenth|"
    "fifteenth|sixteenth|seventeenth|eighteenth|nineteenth|twentieth|thirtieth"
)
NARRATION = {
    "a numbered work period": re.compile(rf"\bsessions?\b|\b(twenty-)?({ORDINALS})[ -](session|period|round)\b", re.I),
    "an issue number": re.compile(r"\bissues? #?\d+", re.I),
    "a run letter": re.compile(r"\brun [A-Z]\b(?!-)"),
    "a UTC time": re.compile(r"\b\d{1,2}:\d{2}(-\d{1,2}:\d{2})? ?UTC\b"),
}


def test_readme_is_short() -> None:
    assert len(README.read_text().splitlines()) <= 300


@pytest.mark.parametrize("path", USER_TEXT + CODE_TEXT, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_narration_of_past_work(path: Path) -> None:
    text = path.read_text()
    found = [
        f"{what}: {m.group(0)!r} at line {text[: m.start()].count(chr(10)) + 1}"
        for what, pattern in NARRATION.items()
        for m in pattern.finditer(text)
    ]
    assert not found, "; ".join(found[:5])


def test_committed_file_names_carry_no_work_period() -> None:
    names = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=False).stdout.split()
    if not names:
        pytest.skip("not a git checkout")
    pattern = re.compile(rf"session|({ORDINALS})_|run_?[a-e](\b|_|\.)|runs_a_b", re.I)
    assert [n for n in names if pattern.search(Path(n).name)] == []


def test_the_api_page_documents_every_public_name() -> None:
    page = (ROOT / "docs" / "reference" / "api.md").read_text()
    documented = set(re.findall(r"^::: rwm_gym\.(\w+)$", page, re.MULTILINE))
    assert documented == set(rwm_gym.EXPORTS)


def test_mkdocs_build_is_strict_clean(tmp_path: Path) -> None:
    pytest.importorskip("mkdocs", reason='needs the docs tools: pip install ".[docs]"')
    pytest.importorskip("mkdocstrings", reason='needs the docs tools: pip install ".[docs]"')
    if shutil.which("git") is None:
        pytest.skip("git not found")
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(tmp_path / "site")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
        timeout=300,
        env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", "NO_MKDOCS_2_WARNING": "1"},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert (tmp_path / "site" / "reference" / "cli" / "index.html").read_text().count("usage: rwm-gym ") == len(
        COMMANDS
    )
