"""The package's top level: the names users import, loaded lazily so `import rwm_gym` stays light."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

import rwm_gym

ROOT = Path(__file__).resolve().parent.parent


def test_import_loads_neither_torch_nor_mujoco() -> None:
    code = (
        "import rwm_gym, sys; heavy = {'torch', 'mujoco', 'stable_baselines3'} & set(sys.modules); "
        "assert not heavy, heavy"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=False,
        env={"PYTHONPATH": str(ROOT), "PATH": ""},
    )
    assert done.returncode == 0, done.stderr[-2000:]


@pytest.mark.parametrize("name", sorted(rwm_gym.EXPORTS))
def test_every_export_is_defined_where_the_map_says(name: str) -> None:
    module = rwm_gym.EXPORTS[name]
    if module in ("rwm_gym.vector.rsl_rl_vec_env", "rwm_gym.rl.rsl_rl_runner"):
        pytest.importorskip("rsl_rl", reason='needs the optional extra: pip install ".[rsl-rl]"')
    assert getattr(rwm_gym, name) is getattr(importlib.import_module(module), name)
    assert name in rwm_gym.__all__ and name in dir(rwm_gym)


def test_an_unknown_name_is_an_attribute_error() -> None:
    with pytest.raises(AttributeError, match="no attribute 'NoSuchThing'"):
        rwm_gym.NoSuchThing  # noqa: B018


def test_version_matches_pyproject() -> None:
    text = (ROOT / "pyproject.toml").read_text()
    assert f'version = "{rwm_gym.__version__}"' in text
