"""Env names: the shipped ids come from envs/*.toml, any spec file works as an env, and bad names fail in one line."""

from __future__ import annotations

import tomllib
from pathlib import Path

import gymnasium as gym
import pytest

import rwm_gym  # noqa: F401  (registers the envs)
from rwm_gym.cli import main
from rwm_gym.registration import IMAGINED_ENVS, PHYSICS_ENVS, resolve_spec
from rwm_gym.resources import specs_dir


def test_every_shipped_spec_registers_its_physics_and_imagined_ids() -> None:
    tasks = [tomllib.loads(p.read_text())["task"] for p in specs_dir().glob("*.toml")]
    assert {t["physics_env_id"] for t in tasks} == set(PHYSICS_ENVS)
    assert {t["imagined_env_id"] for t in tasks} == set(IMAGINED_ENVS)
    assert all(i in gym.registry for i in [*PHYSICS_ENVS, *IMAGINED_ENVS, "Physics-v0", "Imagined-v0"])


def test_a_spec_path_makes_the_same_env_as_its_registered_id(tmp_path: Path) -> None:
    copy = tmp_path / "mine.toml"
    copy.write_text((specs_dir() / "dmc_finger_spin.toml").read_text())
    by_id, by_path = gym.make("DMC-Finger-Spin-v0"), gym.make("rwm_gym:Physics-v0", spec=str(copy))
    assert by_id.observation_space == by_path.observation_space
    a, _ = by_id.reset(seed=3)
    b, _ = by_path.reset(seed=3)
    assert (a == b).all()
    vec = gym.make_vec("rwm_gym:Physics-v0", num_envs=2, spec=str(copy), vectorization_mode="vector_entry_point")
    assert vec.reset(seed=3)[0].shape == (2, *a.shape)


@pytest.mark.parametrize(
    "name, message",
    [
        ("DMC-Swimmer-Swimmer6-v0", "unknown env 'DMC-Swimmer-Swimmer6-v0'"),
        ("missing.toml", "spec file 'missing.toml' not found"),
        ("RWM-Cheetah-v0", "not a physics env"),
    ],
)
def test_unknown_ids_and_bad_spec_paths_fail_in_one_line(name: str, message: str, tmp_path: Path, capsys) -> None:
    with pytest.raises(ValueError, match=message):
        resolve_spec(name)
    assert main(["collect", "--env", name, "--out", str(tmp_path / "x.h5"), "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("rwm-gym collect: ") and message in err
    assert not (tmp_path / "x.h5").exists()


def test_a_malformed_spec_file_fails_in_one_line(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[task]\nname = 'x'\n")
    assert main(["collect", "--env", str(bad), "--out", str(tmp_path / "x.h5"), "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad.toml: missing field" in err
    with pytest.raises(ValueError, match="needs spec=PATH"):
        gym.make("rwm_gym:Physics-v0")
