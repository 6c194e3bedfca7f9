"""Every Python snippet of the README runs when pasted alone into a fresh folder (training budgets made tiny)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parent.parent / "README.md"
SNIPPETS = re.findall(r"```python\n(.*?)```", README.read_text(), re.DOTALL)
TINY_BUDGETS = {"learn(200_000)": "learn(6_144)",  # one rollout of the SB3 snippet's 256 envs
                "num_envs=4096": "num_envs=16", "timesteps=40_000_000": "timesteps=384"}  # the recipe's
NEEDS_EARLIER_STEPS = {"acrobot.safetensors": "the acrobot model of the CLI steps above it (tests/test_new_robot.py)"}


def cases():
    text = README.read_text()
    for code in SNIPPETS:
        line = text[:text.index(code)].count("\n") + 1
        marks = [pytest.mark.slow] if "learn(" in code else []  # trains: a few CPU seconds more
        yield pytest.param(code, id=f"README-line-{line}", marks=marks)


def test_the_readme_has_python_snippets():
    assert len(SNIPPETS) >= 4


@pytest.mark.parametrize("code", list(cases()))
def test_python_snippet_runs_when_pasted_alone(code: str, tmp_path: Path) -> None:
    for needed, why in NEEDS_EARLIER_STEPS.items():
        if needed in code:
            pytest.skip(f"needs {why}")
    if "from rsl_rl" in code:
        pytest.importorskip("rsl_rl", reason="the rsl_rl snippet needs the optional extra: pip install \".[rsl-rl]\"")
    for full, tiny in TINY_BUDGETS.items():
        code = code.replace(full, tiny)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(README.parent)}  # this checkout's package
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                          check=False, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
