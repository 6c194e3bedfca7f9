"""`rwm-gym spec`: specs generated from a dm_control task and from a legged MJCF, and what the command refuses."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import rwm_gym  # noqa: F401  (registers the envs)
from rwm_gym.cli import main
from rwm_gym.spec import load_spec
from tests.legged_mjcf import quadruped_xml


def test_the_cheetah_spec_generated_from_dm_control_has_the_shipped_layout(tmp_path: Path) -> None:
    out = tmp_path / "cheetah.toml"
    assert main(["spec", "--from-dmc", "cheetah-run", "--out", str(out), "--episodes", "2", "--steps", "50"]) == 0
    made, shipped = load_spec(out), load_spec("dmc_cheetah_run")
    assert made.state_columns == shipped.state_columns
    assert made.actuator == shipped.actuator and made.observation == shipped.observation
    assert made.privileged.contact_bodies == shipped.privileged.contact_bodies
    assert made.privileged.feet == shipped.privileged.feet
    assert (made.policy_dt, made.physics_dt, made.episode_steps) == (shipped.policy_dt, shipped.physics_dt, 1000)
    # normalisation measured, not left at placeholders: same order of magnitude as the shipped 16-episode figures
    assert not np.allclose(made.state_std, 1.0)
    ratio = made.state_std / shipped.state_std
    assert np.all((ratio > 0.2) & (ratio < 5.0))


def test_spec_never_overwrites_and_says_why_in_one_line(tmp_path: Path, capsys) -> None:
    out = tmp_path / "acrobot.toml"
    out.write_text("mine")
    assert main(["spec", "--from-dmc", "acrobot-swingup", "--out", str(out)]) == 2
    assert out.read_text() == "mine"
    assert main(["spec", "--from-dmc", "nosuchdomain-run", "--out", str(tmp_path / "x.toml")]) == 2
    assert main(["spec", "--mjcf", str(tmp_path / "missing.xml"), "--out", str(tmp_path / "y.toml")]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 3 and all(line.startswith("rwm-gym spec: ") for line in errors)
    assert "--overwrite" in errors[0] and "nosuchdomain" in errors[1] and "missing.xml" in errors[2]
    assert not (tmp_path / "x.toml").exists() and not (tmp_path / "y.rwm.xml").exists()


@pytest.fixture(scope="module")
def legged_spec(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("legged")
    (folder / "robot.xml").write_text(quadruped_xml())
    out = folder / "quad.toml"
    assert (
        main(["spec", "--mjcf", str(folder / "robot.xml"), "--out", str(out), "--episodes", "2", "--steps", "50"]) == 0
    )
    return out


def test_a_legged_mjcf_becomes_a_spec_and_a_physics_env_that_stands(legged_spec: Path) -> None:
    spec = load_spec(legged_spec)
    assert spec.actuator.joints == tuple(f"{leg}_{j}" for leg in ("fl", "fr", "hl", "hr") for j in ("hip", "knee"))
    assert spec.privileged.feet == tuple(f"{leg}_shin_foot" for leg in ("fl", "fr", "hl", "hr"))
    assert spec.privileged.termination_bodies == ("torso",) and spec.policy_dt == pytest.approx(0.02)
    assert Path(spec.model).is_file() and Path(spec.model).parent == legged_spec.parent
    assert "Assumed by `rwm-gym spec`" in legged_spec.read_text()
    env = gym.make("rwm_gym:Physics-v0", spec=str(legged_spec))
    check_env(env.unwrapped, skip_render_check=True)
    env.reset(seed=0)
    height0 = env.unwrapped.data.qpos[2]
    for _ in range(50):  # zero action holds the default pose: the robot stands on its feet
        _, _, terminated, _, _ = env.step(np.zeros(env.action_space.shape, np.float32))
        assert not terminated
    core = env.unwrapped.core
    assert env.unwrapped.data.qpos[2] > 0.8 * height0
    assert core.current.contact[0, 4:].sum() >= 2  # feet touch the floor ...
    assert not core.current.contact[0, :4].any()  # ... the thighs do not
    assert np.all(np.abs(core.current.foot_height) < 0.01)


def test_the_spec_of_a_legged_mjcf_is_refused_without_a_floating_base(tmp_path: Path, capsys) -> None:
    (tmp_path / "arm.xml").write_text(
        '<mujoco><worldbody><body name="a"><joint name="j"/><geom size="0.1"/></body></worldbody></mujoco>'
    )
    assert main(["spec", "--mjcf", str(tmp_path / "arm.xml"), "--out", str(tmp_path / "arm.toml")]) == 2
    assert "free-floating base" in capsys.readouterr().err
