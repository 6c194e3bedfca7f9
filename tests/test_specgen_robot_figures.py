"""`rwm-gym spec --mjcf`: each joint's own gains and limits from the file, the command rule, and fast physics."""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest

from rwm_gym.cli import main
from rwm_gym.spec import load_spec
from rwm_gym.specgen.from_mjcf import FROUDE, command_speed
from tests.legged_mjcf import classed_quadruped_xml, quadruped_xml

JOINTS = [f"{leg}_{j}" for leg in ("fl", "fr", "hl", "hr") for j in ("hip", "knee")]


def _spec(tmp_path: Path, xml: str, *flags: str) -> Path:
    (tmp_path / "robot.xml").write_text(xml)
    out = tmp_path / "robot.toml"
    args = ["spec", "--mjcf", str(tmp_path / "robot.xml"), "--out", str(out), "--episodes", "1", "--steps", "20"]
    assert main([*args, *flags]) == 0
    return out


def test_per_class_servo_gains_and_force_ranges_reach_each_joint(tmp_path: Path) -> None:
    spec = load_spec(_spec(tmp_path, classed_quadruped_xml()))
    act = spec.actuator
    assert act.per_joint("kp").tolist() == [12.0, 18.0] * 4
    assert act.per_joint("kd").tolist() == [0.3, 0.4] * 4
    assert act.per_joint("effort_limit").tolist() == [4.0, 7.0] * 4  # the hip's forcerange, the knee's joint range
    model = mujoco.MjModel.from_xml_path(spec.model)  # the copy's servos carry the same figures
    knee = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, "fl_knee")
    assert model.actuator_gainprm[knee, 0] == 18.0 and model.actuator_forcerange[knee].tolist() == [-7.0, 7.0]
    assert act.default_pose == (0.2, -0.4) * 4 and spec.keyframe == "stand"


def test_motor_actuators_give_their_control_range_as_the_limit_and_the_gains_come_from_weight(tmp_path: Path) -> None:
    out = _spec(tmp_path, quadruped_xml().replace('ctrlrange="-3 3"/>', 'ctrlrange="-3 3" gear="2"/>', 4))
    act = load_spec(out).actuator
    assert act.per_joint("effort_limit").tolist() == [6.0] * 4 + [3.0] * 4  # the first four motors have gear 2
    assert isinstance(act.kp, float) and act.kp > 0 and act.kd == pytest.approx(act.kp / 10, rel=1e-3)
    assert "kp = 2 x weight x standing height" in out.read_text()


def test_commands_follow_the_froude_rule_which_gives_anymal_d_its_own_range() -> None:
    anymal = load_spec("anymal_d")
    height = 0.5885  # ANYmal D's keyframe base height
    assert command_speed(height) == max(anymal.command.high) == 1.0
    assert command_speed(0.1) == pytest.approx(np.sqrt(FROUDE * 9.81 * 0.1), abs=0.01)  # a small robot: slower
    assert command_speed(0.27) == 1.0  # a Go2: the cap


def test_fast_physics_takes_anymal_d_solver_and_states_its_speed_and_accuracy(tmp_path: Path, capsys) -> None:
    out = _spec(tmp_path, classed_quadruped_xml(), "--fast-physics")
    printed = capsys.readouterr().out
    assert "fast physics measured" in printed and "x the file's solver" in printed
    spec = load_spec(out)
    model = mujoco.MjModel.from_xml_path(spec.model)
    anymal = mujoco.MjModel.from_xml_path(str(load_spec("anymal_d").model_path))
    for name in ("cone", "iterations", "ls_iterations", "noslip_iterations", "timestep"):
        assert getattr(model.opt, name) == getattr(anymal.opt, name), name
    assert spec.physics_dt == 0.005 and spec.policy_dt == pytest.approx(0.02)
    robot = [g for g in range(model.ngeom) if model.geom_bodyid[g] > 0]
    assert all(model.geom_condim[g] == 3 and model.geom_contype[g] == 2 for g in robot)


def test_fast_physics_is_refused_for_a_dm_control_task(tmp_path: Path, capsys) -> None:
    args = ["spec", "--from-dmc", "acrobot-swingup", "--out", str(tmp_path / "a.toml"), "--fast-physics"]
    assert main(args) == 2
    assert "--fast-physics" in capsys.readouterr().err


def test_score_takes_a_generated_spec_and_scores_on_its_own_commands(tmp_path: Path, capsys) -> None:
    out = _spec(tmp_path, classed_quadruped_xml(elliptic=False))
    folder = tmp_path / "score"
    args = ["score", "--policy", "zero", "--env", str(out), "--out", str(folder), "--seeds", "1", "--commands", "2"]
    assert main([*args, "--steps", "60"]) == 0
    report = json.loads((folder / "score.json").read_text())
    spec = load_spec(out)
    assert report["task"] == spec.name == "ClassedQuad"
    high = max(spec.command.high)
    assert high < 1.0  # a 0.24 m robot: the Froude rule's speed, below ANYmal D's
    commands = [row["command"] for row in report["evaluation"]["commands"]]
    assert all(abs(c) <= high + 1e-9 for command in commands for c in command)
    assert commands[1][0] == pytest.approx(high)  # "1 m/s forward" is the top of its forward range
