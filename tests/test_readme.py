"""Every Python snippet of the README and of the docs runs when pasted alone into a fresh folder (training budgets
made tiny).

Blocks fenced as `python` run; blocks fenced as `py` are illustrations that need files made by earlier steps on their
page (a checkpoint trained there) and are shown, not run.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").rglob("*.md"))]
TINY_BUDGETS = {
    "learn(200_000)": "learn(6_144)",  # one rollout of the SB3 snippet's 256 envs
    "num_envs=4096": "num_envs=16",
    "timesteps=40_000_000": "timesteps=384",  # the recipe's
    "num_learning_iterations=50": "num_learning_iterations=1",
}


def snippets(page: Path) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", page.read_text(), re.DOTALL | re.MULTILINE)


def cases():
    for page in PAGES:
        text = page.read_text()
        for code in snippets(page):
            line = text[: text.index(code)].count("\n") + 1
            trains = "learn(" in code
            marks = [pytest.mark.slow] if trains else []  # trains: a few CPU seconds more
            yield pytest.param(code, id=f"{page.relative_to(ROOT)}-line-{line}", marks=marks)


def test_the_readme_has_python_snippets():
    assert len(snippets(README)) >= 4


@pytest.mark.parametrize("code", list(cases()))
def test_python_snippet_runs_when_pasted_alone(code: str, tmp_path: Path) -> None:
    if "from rsl_rl" in code:
        pytest.importorskip("rsl_rl", reason='the rsl_rl snippet needs the optional extra: pip install ".[rsl-rl]"')
    for full, tiny in TINY_BUDGETS.items():
        code = code.replace(full, tiny)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}  # this checkout's package
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, check=False, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
