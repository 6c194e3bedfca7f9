"""The kinematic closure of a fixed-base arm: angles integrate velocities, sites follow by forward kinematics, checked
against dm_control's physics; other robots are left alone."""

import numpy as np
import pytest

from rwm_gym.imagination.kinematics import KinematicClosure
from rwm_gym.physics.dmc import make_core
from rwm_gym.spec import load_spec


@pytest.fixture(scope="module")
def reach_rollout():
    """Physics states of 4 envs over 30 steps of correlated random actions on the Jaco reach."""
    core = make_core("dmc_jaco_reach_site", 4)
    core.reset(np.arange(4), [0, 1, 2, 3])
    rng = np.random.default_rng(0)
    states, action = [core.state.copy()], np.zeros((4, core.spec.action_dim))
    for _ in range(30):
        action = np.clip(0.9 * action + 0.3 * rng.standard_normal(action.shape), -1, 1)
        core.step(action.astype(np.float32))
        states.append(core.state.copy())
    return core.spec, np.array(states, dtype=np.float64)


def test_sites_on_the_arm_are_the_forward_kinematics_of_its_angles(reach_rollout):
    spec, states = reach_rollout
    closure = KinematicClosure.of(spec)
    hand = [spec.state_columns.index(f"site_pos/jaco_arm/jaco_hand/pinchsite:{c}") for c in "xyz"]
    target = [spec.state_columns.index(f"site_pos/target_site:{c}") for c in "xyz"]
    assert [columns for columns, _ in closure.sites] == [hand]  # the target is not on the arm
    for t in (1, 10, 30):
        placed = states[t].copy()
        placed[:, hand] += 0.3  # wrong on purpose: the closure puts it back
        closure.apply(states[t - 1], placed)
        assert np.abs(placed[:, hand] - states[t][:, hand]).max() < 5e-3  # the integrated angles, then FK
        assert np.array_equal(placed[:, target], states[t][:, target])


def test_integrated_angles_follow_physics_to_a_fraction_of_a_step(reach_rollout):
    spec, states = reach_rollout
    closure = KinematicClosure.of(spec)
    angles = [angle for angle, _, _ in closure.plain] + [c for c, _, _, _ in closure.circular]
    assert len(closure.plain) == 5 and len(closure.circular) == 4  # two limited arm joints + 3 fingers; 4 unlimited
    errors, motion = [], []
    for t in range(1, len(states)):
        integrated = states[t].copy()
        integrated[:, angles] = 0.0
        closure.apply(states[t - 1], integrated)
        errors.append(np.abs(integrated[:, angles] - states[t][:, angles]))
        motion.append(np.abs(states[t][:, angles] - states[t - 1][:, angles]))
    # the trapezoid over one policy step: a small share of the step's motion (what copying the last angle misses)
    assert np.mean(errors) < 0.15 * np.mean(motion)


def test_only_fixed_base_arms_have_a_closure():
    assert KinematicClosure.of(load_spec("anymal_d")) is None
    assert KinematicClosure.of(load_spec("dmc_cheetah_run")) is None
