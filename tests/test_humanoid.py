"""A humanoid on the legged path: `rwm-gym spec --mjcf` on a small MJX-style humanoid (box and capsule feet, every
contact off but explicit pairs, per-class servos, two keyframes), the biped reward terms (numpy == torch; absent or
zero weights change nothing), and the shipped Unitree G1 (falls at zero action; the legs-only variant holds its
arms; its mirror table is its physics' mirror)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch

import rwm_gym  # noqa: F401  (registers the envs)
from rwm_gym.cli import main
from rwm_gym.physics.locomotion import LocomotionCore
from rwm_gym.spec import ResetSpec, RewardSpec, load_spec, parse_spec
from rwm_gym.task import reward, reward_torch
from rwm_gym.task.symmetry import action_mirror, state_mirror

LEG = """
      <body name="{s}_thigh" pos="0 {y} -0.05">
        <joint name="{s}_hip" class="hip"/>
        <geom name="{s}_thigh_geom" class="col" fromto="0 0 0 0 0 -0.2" size="0.04"/>
        <body name="{s}_shin" pos="0 0 -0.2">
          <joint name="{s}_knee" class="knee"/>
          <geom name="{s}_shin_geom" class="col" fromto="0 0 0 0 0 -0.2" size="0.035"/>
          <body name="{s}_foot" pos="0 0 -0.2">
            <joint name="{s}_ankle" class="ankle"/>
            <geom name="{s}_sole" type="box" pos="0.03 0 -0.03" size="0.1 0.05 0.01" mass="0.3"/>
            <geom name="{s}_toe" class="col" fromto="0.1 0 -0.03 -0.05 0 -0.03" size="0.012"/>
            <geom name="{s}_heel" class="col" fromto="0.1 {w} -0.03 -0.05 {w} -0.03" size="0.012"/>
          </body>
        </body>
      </body>
      <body name="{s}_arm" pos="0 {a} 0.3">
        <joint name="{s}_shoulder" class="hip"/>
        <geom name="{s}_hand" class="col" fromto="0 0 0 0 0 -0.25" size="0.03"/>
      </body>"""

SIDES = (("l", 0.1, 0.03, 0.2), ("r", -0.1, -0.03, -0.2))


def humanoid_xml() -> str:
    """A 6 kg humanoid, MJX-style: contype = conaffinity = 0 on every robot geom, the soles' capsules and the hands
    touch the floor through `<pair>`s only, the two sole boxes touch each other; position servos per class."""
    body = "".join(LEG.format(s=s, y=y, w=w, a=a) for s, y, w, a in SIDES)
    pairs = (
        "".join(
            f'<pair geom1="{s}_{g}" geom2="floor"/>' for s, *_ in SIDES for g in ("toe", "heel", "hand", "shin_geom")
        )
        + '<pair geom1="l_sole" geom2="r_sole" condim="1"/>'
    )
    servos = "".join(
        f'<position class="{c}" joint="{s}_{j}"/>'
        for s, *_ in SIDES
        for j, c in (("hip", "hip"), ("knee", "knee"), ("ankle", "ankle"), ("shoulder", "hip"))
    )
    stand = "0 0 0.493 1 0 0 0 " + " ".join(["0 0 0 0"] * 2)
    crouch = "0 0 0.45 1 0 0 0 " + " ".join(["-0.4 0.8 -0.4 0"] * 2)
    return f"""<mujoco model="tiny humanoid">
  <option timestep="0.004" integrator="implicitfast"/>
  <default>
    <default class="robot">
      <geom contype="0" conaffinity="0" density="500"/>
      <joint axis="0 1 0" range="-1.5 1.5" actuatorfrcrange="-30 30"/>
      <position kp="60" kv="2"/>
      <default class="col"><geom type="capsule"/></default>
      <default class="hip"/>
      <default class="knee"><joint range="-0.1 2"/></default>
      <default class="ankle"><joint range="-0.8 0.8" actuatorfrcrange="-12 12"/><position kp="15" kv="1"/></default>
    </default>
  </default>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.1"/>
    <body name="pelvis" pos="0 0 0.5" childclass="robot">
      <freejoint/>
      <geom name="torso" type="box" size="0.08 0.12 0.2" pos="0 0 0.15" mass="3"/>{body}
    </body>
  </worldbody>
  <contact>{pairs}</contact>
  <actuator>{servos}</actuator>
  <keyframe><key name="crouch" qpos="{crouch}"/><key name="stand" qpos="{stand}"/></keyframe>
</mujoco>
"""


def _spec(tmp_path: Path, *flags: str, xml: str | None = None) -> tuple[int, Path]:
    (tmp_path / "humanoid.xml").write_text(xml or humanoid_xml())
    out = tmp_path / "humanoid.toml"
    args = ["spec", "--mjcf", str(tmp_path / "humanoid.xml"), "--out", str(out), "--episodes", "1", "--steps", "10"]
    return main([*args, *flags]), out


def test_a_humanoid_gets_its_two_feet_the_keyframe_it_names_and_its_servos(tmp_path: Path, capsys) -> None:
    status, out = _spec(tmp_path, "--keyframe", "stand")
    assert status == 0
    printed = capsys.readouterr().out
    assert "l_arm (0.51 m up)" in printed and "not feet" in printed  # the hands are leaves, up in the air: said so
    spec = load_spec(out)
    assert spec.privileged.feet == ("l_toe", "r_toe")  # the lowest round end of each sole names the foot
    assert spec.privileged.thighs == ("l_shin", "r_shin")
    assert spec.reward.weights == load_spec("g1").reward.weights and spec.reward.base_height_target == 0.493
    assert "base_height" in spec.state_slices  # the biped terms read it
    assert spec.keyframe == "stand" and spec.actuator.default_pose == (0.0,) * 8
    assert spec.actuator.per_joint("kp").tolist() == [60, 60, 15, 60] * 2
    assert spec.actuator.per_joint("effort_limit").tolist() == [30, 30, 12, 30] * 2
    model = mujoco.MjModel.from_xml_path(spec.model)
    data = mujoco.MjData(model)
    key = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, "stand")
    mujoco.mj_resetDataKeyframe(model, data, key)
    data.ctrl[:] = 0.0
    mujoco.mj_step(model, data, 100)  # 0.4 s: settled on the soles' capsules, every contact a pair's
    assert data.ncon and all(c.exclude == 0 for c in data.contact[: data.ncon])
    feet = [model.sensor(f"contact_{foot}") for foot in spec.privileged.feet]
    load = sum(float(data.sensordata[s.adr[0]]) for s in feet)
    weight = float(model.body_subtreemass[1]) * 9.81
    assert load == pytest.approx(weight, rel=0.05)  # the touch sites see the pair contacts of the whole sole
    site = model.site("contact_l_toe")
    assert site.type[0] == mujoco.mjtGeom.mjGEOM_BOX  # a box around the sole's box and capsules


def test_the_first_keyframe_is_the_default_and_a_missing_one_is_named_in_one_line(tmp_path: Path, capsys) -> None:
    status, out = _spec(tmp_path)
    assert status == 0 and load_spec(out).keyframe == "crouch"
    status, _ = _spec(tmp_path, "--keyframe", "sit", "--overwrite")
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1
    assert "--keyframe 'sit': no such keyframe" in err and "'crouch', 'stand'" in err


def test_feet_named_by_hand_still_win_and_a_robot_that_cannot_touch_the_floor_is_refused(tmp_path: Path, capsys):
    status, out = _spec(tmp_path, "--feet", "l_foot", "r_foot", "l_arm", "--keyframe", "stand")
    assert status == 0 and load_spec(out).privileged.feet == ("l_toe", "r_toe", "l_hand")
    no_pairs = humanoid_xml().split("<contact>")[0] + humanoid_xml().split("</contact>")[1]
    status, _ = _spec(tmp_path, "--overwrite", xml=no_pairs)
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1 and "can touch the floor" in err


def _biped_batch(spec, n: int = 64, seed: int = 0):
    rng = np.random.default_rng(seed)
    state = rng.normal(size=(n, spec.state_dim)) * spec.state_std + spec.state_mean
    prev = rng.normal(size=(n, spec.state_dim)) * spec.state_std + spec.state_mean
    contact = rng.random((n, spec.contact_dim)) < 0.5
    command = rng.uniform(-1, 1, (n, 3))
    command[: n // 4] = 0.0  # standing rows: single_stance pays nothing there
    action, prev_action = rng.uniform(-1, 1, (2, n, spec.action_dim))
    air = rng.normal(size=n)
    return state, prev, contact, command, action, prev_action, air


def test_the_biped_terms_are_the_same_in_numpy_and_torch() -> None:
    spec = load_spec("g1")
    batch = _biped_batch(spec)
    terms = reward.reward_terms(spec, *batch)
    assert {"base_height", "feet_slip", "single_stance"} <= set(terms)
    got = reward_torch.reward_terms(spec, *(torch.as_tensor(x) for x in batch))
    assert set(got) == set(terms)
    for name, value in terms.items():
        np.testing.assert_allclose(got[name].numpy(), value, rtol=1e-12, atol=1e-12, err_msg=name)
    np.testing.assert_allclose(
        reward_torch.total_reward(spec, got).numpy(), reward.total_reward(spec, terms), rtol=1e-12, atol=1e-12
    )
    state, _, contact, command, *_ = batch
    feet = contact[:, 2:].sum(axis=1)  # contact bodies: two knees, then the two feet
    moving = np.linalg.norm(command[:, :2], axis=1) > spec.command.standing_threshold
    np.testing.assert_array_equal(terms["single_stance"], (feet == 1) & moving)
    assert terms["single_stance"][: len(state) // 4].sum() == 0 and terms["single_stance"].sum() > 0
    height = state[:, spec.state_slices["base_height"]][:, 0]
    np.testing.assert_allclose(terms["base_height"], (height - 0.755) ** 2)
    lin = state[:, spec.state_slices["base_lin_vel"]]
    np.testing.assert_allclose(terms["feet_slip"], (lin[:, :2] ** 2).sum(axis=1) * feet)


def test_absent_or_zero_biped_weights_leave_anymal_d_and_go2_rewards_bit_identical() -> None:
    for name in ("anymal_d", "go2"):
        spec = load_spec(name)
        batch = _biped_batch(spec, seed=1)
        terms = reward.reward_terms(spec, *batch)
        assert set(terms) == set(spec.reward.weights)  # no biped term computed
        legacy = sum(spec.reward.weights[k] * terms[k] for k in spec.reward.weights) * spec.policy_dt
        total = reward.total_reward(spec, terms)
        assert np.array_equal(total, legacy)
        zeros = {**spec.reward.weights, "base_height": 0.0, "feet_slip": 0.0, "single_stance": 0.0}
        zeroed = replace(spec, reward=RewardSpec(zeros, spec.reward.tracking_sigma, spec.reward.feet_air_time_target))
        again = reward.reward_terms(zeroed, *batch)
        assert set(again) == set(terms) and np.array_equal(reward.total_reward(zeroed, again), total)


def test_a_base_height_weight_without_its_state_group_or_target_is_refused_in_one_line() -> None:
    text = load_spec("anymal_d").text.replace("flat_orientation = -5.0", "flat_orientation = -5.0\nbase_height = -1")
    with pytest.raises(ValueError, match=r"needs \[reward\] base_height_target .* state group 'base_height'"):
        parse_spec(text, where="x.toml")


def test_the_g1_falls_at_zero_action_and_its_legs_only_variant_holds_the_arms() -> None:
    env = gym.make("G1-MuJoCo-v0")
    assert env.observation_space.shape == (99,) and env.action_space.shape == (29,)
    env.reset(seed=0, options={"command": (0.0, 0.0, 0.0)})
    contact = env.unwrapped.core.current.contact[0]
    assert contact[2:].all() and not contact[:2].any()  # on its feet, knees clear
    steps, terminated = 0, False
    while not terminated and steps < 150:  # 3 s
        terminated = env.step(np.zeros(29, np.float32))[2]
        steps += 1
    assert terminated and 20 < steps < 150  # stands a moment, then topples: the ankles' kp 20 cannot hold 33 kg
    legs = gym.make("G1Legs-MuJoCo-v0")
    assert legs.action_space.shape == (12,)
    legs.reset(seed=0)
    for _ in range(10):
        legs.step(np.zeros(12, np.float32))
    model, data = legs.unwrapped.model, legs.unwrapped.data
    key = model.key("knees_bent").id
    held = [model.actuator(name).id for name in ("left_elbow_joint", "waist_pitch_joint")]
    np.testing.assert_array_equal(data.ctrl[held], model.key_ctrl[key][held])  # not 0 rad: the keyframe's pose


def test_fast_physics_keeps_the_explicit_pairs_and_says_so(tmp_path: Path, capsys) -> None:
    status, out = _spec(tmp_path, "--fast-physics", "--keyframe", "stand")
    assert status == 0 and "the file's 9 explicit contact pairs stay" in capsys.readouterr().out
    model = mujoco.MjModel.from_xml_path(load_spec(out).model)
    assert model.npair == 9 and (model.geom_contype == 0).sum() == model.ngeom - 1  # the floor alone has bits


def test_the_g1_mirror_table_is_its_physics_mirror() -> None:
    """A mirrored action sequence from the (symmetric) keyframe gives the mirrored state: the joint map and signs of
    `[symmetry]` match the model's axes. The unmirrored states differ by radians, so a wrong sign cannot pass."""
    spec = replace(load_spec("g1"), reset=ResetSpec())
    act, state = action_mirror(spec), state_mirror(spec)
    cores = [LocomotionCore(spec) for _ in range(2)]
    for core in cores:
        core.reset(np.array([0]))
    groups = ("base_lin_vel", "base_ang_vel", "projected_gravity", "base_height", "joint_pos")
    kept = np.concatenate([np.arange(spec.state_dim)[spec.state_slices[g]] for g in groups])
    rng = np.random.default_rng(0)
    for _ in range(5):
        a = rng.uniform(-0.3, 0.3, (1, spec.action_dim))
        cores[0].step(a)
        cores[1].step(a[:, act.index] * act.sign)
        one, other = (core.current.state[0] for core in cores)
        assert np.abs((one[state.index] * state.sign - other)[kept]).max() < 0.02
        assert np.abs((one - other)[kept]).max() > 0.5


def test_feet_air_time_pays_each_of_two_feet_its_swing_at_touchdown() -> None:
    """A walking biped's alternating steps: each touchdown pays that foot's swing time less the target, once; both feet
    down pays nothing (the timers are those of any number of feet)."""
    dt, target, swing = 0.02, 0.2, 15  # 0.3 s swings
    timers = reward.FeetAirTime(1, 2)
    payouts = []
    for step in range(4 * swing):
        left_up = (step // swing) % 2 == 1
        contact = np.array([[not left_up, left_up or step < swing]])
        payouts.append(float(timers.update(contact, dt, target)[0]))
    paid = {i: p for i, p in enumerate(payouts) if p != 0.0}
    assert list(paid) == [2 * swing, 3 * swing]  # the left foot lands, then the right; both down before: nothing
    for p in paid.values():
        assert p == pytest.approx(swing * dt - target)  # 0.3 s - 0.2 s, the flicker filter's step included
    with pytest.raises(ValueError, match="needs checkpoint=PATH"):
        gym.make("RWM-G1-v0")
