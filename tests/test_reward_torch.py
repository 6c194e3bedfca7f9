"""The torch reward (`rwm_gym.task.reward_torch`) is the numpy reward on tensors: equal terms, totals and feet-air-time
timers over recorded ANYmal D episodes, with gradients reaching the state and the action."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from rwm_gym.data.dataset import Dataset
from rwm_gym.resources import shipped_file
from rwm_gym.task import reward, reward_torch
from rwm_gym.task.tasks import VelocityTrackingTask


def _episodes(name: str) -> tuple[Dataset, dict[str, np.ndarray]]:
    """Every episode of a shipped dataset side by side: {field: (E, Lmax+1, ...)}, short episodes padded with their last
    row, plus "length" (E,) transitions per episode."""
    data = Dataset.load(shipped_file(f"assets/checkpoints/{name}.h5"))
    rows = int(data.episode_lengths.max())
    episodes = [data.episode(i) for i in range(data.num_episodes)]
    batch = {
        key: np.stack(
            [np.concatenate([ep[key], np.repeat(ep[key][-1:], rows - len(ep[key]), axis=0)]) for ep in episodes]
        )
        for key in ("state", "contact", "command", "action", "reward")
    }
    batch["length"] = data.episode_lengths - 1
    return data, batch


@pytest.fixture(scope="module", params=["anymal_d_reset", "anymal_d_demos"])
def recorded(request):
    return _episodes(request.param)


@pytest.mark.parametrize("commands", ["recorded", "standing"])
def test_torch_reward_equals_numpy_reward_step_by_step_over_recorded_episodes(recorded, commands):
    """All episodes of a dataset run as parallel envs through the numpy task and the torch reward in float64: every
    term, the total and the timers agree at every step; with the recorded commands the total is the recorded reward.
    "standing" zeroes the commands, so stand_still and the standing branch of the air-time term are compared too."""
    data, ep = recorded
    ep = {key: value.astype(np.float64) if value.dtype == np.float32 else value for key, value in ep.items()}
    spec = data.spec()
    num_envs, steps = len(ep["length"]), ep["length"].max()
    task = VelocityTrackingTask(spec, num_envs)  # numpy, exactly as the physics env composes it
    timers = reward_torch.FeetAirTime(num_envs, spec.foot_dim, dtype=torch.float64)
    command = ep["command"] if commands == "recorded" else np.zeros_like(ep["command"])
    last_action = np.zeros_like(ep["action"][:, 0])
    touchdowns = thigh_contacts = 0
    for t in range(steps):
        active = t < ep["length"]  # padded rows of finished episodes run but are not compared
        args = ep["state"][:, t + 1], ep["state"][:, t], ep["contact"][:, t + 1]
        action = ep["action"][:, t]
        task.command = command[:, t]
        expected, expected_terms = task.reward(*args, None, action, last_action)
        got, got_terms = reward_torch.velocity_tracking_reward(
            spec,
            timers,
            *(torch.as_tensor(a, dtype=torch.float64) for a in args[:2]),
            torch.as_tensor(args[2]),
            torch.as_tensor(command[:, t], dtype=torch.float64),
            torch.as_tensor(action, dtype=torch.float64),
            torch.as_tensor(last_action, dtype=torch.float64),
        )
        assert set(got_terms) == set(expected_terms)
        for name, value in expected_terms.items():
            np.testing.assert_allclose(
                got_terms[name].numpy()[active], value[active], rtol=1e-12, atol=1e-12, err_msg=f"step {t}, term {name}"
            )
        np.testing.assert_allclose(got.numpy()[active], expected[active], rtol=1e-12, atol=1e-12, err_msg=f"step {t}")
        np.testing.assert_array_equal(timers.air_time.numpy(), task.air_time.air_time)
        np.testing.assert_array_equal(timers.last_contact.numpy(), task.air_time.last_contact)
        if commands == "recorded":
            np.testing.assert_allclose(got.numpy()[active], ep["reward"][active, t], atol=1e-6)  # float32 record
        touchdowns += int((expected_terms["feet_air_time"][active] != 0).sum())
        thigh_contacts += int((expected_terms["thigh_contact"][active] != 0).sum())
        last_action = action
    assert touchdowns > 0 if commands == "recorded" else touchdowns == 0  # the timers' payout was exercised
    if data.path.stem == "anymal_d_reset":
        assert thigh_contacts > 0


def _transitions(ep, rows: int, dtype: torch.dtype):
    """`rows` recorded transitions (of different episodes, late enough to have a previous action) as tensors; the
    last half with a zero command (standing)."""
    t = 10
    command = ep["command"][:rows, t].copy()
    command[rows // 2 :] = 0.0
    return [
        torch.as_tensor(a, dtype=dtype)
        for a in (
            ep["state"][:rows, t + 1],
            ep["state"][:rows, t],
            command,
            ep["action"][:rows, t],
            ep["action"][:rows, t - 1],
        )
    ]


def test_gradients_reach_the_predicted_state_and_the_action(recorded):
    """d reward / d (state, prev_state, action, prev_action) is what autograd's finite differences say, and the
    velocity-tracking terms pull base_lin_vel where a command asks for motion."""
    data, ep = recorded
    spec = data.spec()
    state, prev_state, command, action, prev_action = _transitions(ep, 4, torch.float64)
    contact = torch.as_tensor(ep["contact"][:4, 11])
    air = torch.zeros(4, dtype=torch.float64)

    def total(state, prev_state, action, prev_action):
        terms = reward_torch.reward_terms(spec, state, prev_state, contact, command, action, prev_action, air)
        return reward_torch.total_reward(spec, terms)

    inputs = [x.requires_grad_() for x in (state, prev_state, action, prev_action)]
    assert torch.autograd.gradcheck(total, inputs)
    total(*inputs).sum().backward()
    lin_vel = spec.state_slices["base_lin_vel"]
    assert (state.grad[:2, lin_vel][:, :2] != 0).all()  # moving rows: tracking pulls v_xy toward the command
    assert (action.grad != 0).any() and (prev_action.grad != 0).any()  # action rate
    assert (prev_state.grad[:, spec.state_slices["joint_vel"]] != 0).any()  # dof_acc
    assert (state.grad[2:, spec.state_slices["joint_pos"]] != 0).all()  # standing rows: stand_still


def test_float32_tensors_with_0_1_contacts(recorded):
    """The reward runs in float32 (the world model's dtype) with float 0/1 contacts, close to the float64 numpy one."""
    data, ep = recorded
    spec = data.spec()
    state, prev_state, command, action, prev_action = _transitions(ep, 6, torch.float32)
    contact = ep["contact"][:6, 11]
    timers = reward_torch.FeetAirTime(6, spec.foot_dim)
    got, terms = reward_torch.velocity_tracking_reward(
        spec,
        timers,
        state,
        prev_state,
        torch.as_tensor(contact * 1.0, dtype=torch.float32),
        command,
        action,
        prev_action,
    )
    assert got.dtype == torch.float32 and all(term.dtype == torch.float32 for term in terms.values())
    assert timers.air_time.dtype == torch.float32

    feet = np.isin(spec.privileged.contact_bodies, spec.privileged.feet)
    numpy_timers = reward.FeetAirTime(6, spec.foot_dim)
    air = numpy_timers.update(contact[:, feet], spec.policy_dt, spec.reward.feet_air_time_target)
    expected_terms = reward.reward_terms(
        spec,
        *(x.double().numpy() for x in (state, prev_state)),
        contact,
        *(x.double().numpy() for x in (command, action, prev_action)),
        air,
    )
    np.testing.assert_allclose(got.numpy(), reward.total_reward(spec, expected_terms), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(timers.air_time.numpy(), numpy_timers.air_time, rtol=1e-6)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no cuda device visible to torch")
def test_on_cuda_the_reward_and_timers_stay_on_the_device_and_match_the_cpu(recorded):
    data, ep = recorded
    spec = data.spec()
    results = {}
    for device in ("cpu", "cuda"):
        timers = reward_torch.FeetAirTime(len(ep["length"]), spec.foot_dim, device=device)
        for t in range(1, 40):
            tensors = [
                torch.as_tensor(a, device=device)
                for a in (
                    ep["state"][:, t + 1],
                    ep["state"][:, t],
                    ep["contact"][:, t + 1],
                    ep["command"][:, t],
                    ep["action"][:, t],
                    ep["action"][:, t - 1],
                )
            ]
            got, _terms = reward_torch.velocity_tracking_reward(spec, timers, *tensors)
        assert got.device.type == device and timers.air_time.device.type == device
        results[device] = got.cpu(), timers.air_time.cpu()
    for cpu, cuda in zip(results["cpu"], results["cuda"]):
        torch.testing.assert_close(cuda, cpu, rtol=1e-5, atol=1e-6)
