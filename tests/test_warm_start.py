"""Behaviour cloning of the shipped trot data into an SB3 PPO actor: pairs, fit, log std, held-out error."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from rwm_gym.data.dataset import Dataset, write_dataset
from rwm_gym.rl.ppo import PPOConfig, make_env, make_ppo
from rwm_gym.rl.warm_start import CloneConfig, action_mse, behaviour_clone, default_demonstrations, demonstrations

TINY = PPOConfig(num_envs=2, n_steps=16, num_minibatches=1, net_arch=(64, 64))


@pytest.fixture(scope="module")
def trot(tmp_path_factory) -> Dataset:
    """24 episodes of the shipped scripted-trot demonstrations that do not end in a fall, 80 rows each."""
    demos = Dataset.load(default_demonstrations())
    keep = [i for i in range(demos.num_episodes) if not demos.episode(i)["terminated"].any()][:24]
    path = tmp_path_factory.mktemp("trot") / "trot.h5"

    def first_rows(i: int) -> dict[str, np.ndarray]:
        episode = {k: v[:80].copy() for k, v in demos.episode(i).items()}
        episode["action"][-1], episode["reward"][-1], episode["truncated"][-1] = 0.0, 0.0, True
        return episode

    write_dataset(path, demos.info, (first_rows(i) for i in keep))
    return Dataset.load(path)


def test_pairs_follow_the_dataset_layout(trot):
    demos = demonstrations([trot], drop_before_fall=50)
    spec = trot.spec()
    # every episode loses its last row (no transition); none of these episodes ends in a fall
    assert len(demos.actions) == trot.num_steps - trot.num_episodes
    assert demos.observations.shape == (len(demos.actions), 48) and demos.actions.shape[1] == spec.action_dim
    assert np.array_equal(demos.actions[:3], trot["action"][:3])
    last = slice(36, 48)  # last_action: zero at the first row, the previous row's action after it
    assert not demos.observations[0, last].any()
    assert np.array_equal(demos.observations[1, last], trot["action"][0])
    assert len(np.unique(demos.episode)) == trot.num_episodes


def test_cloning_fits_the_logged_actions(trot):
    model = make_ppo(make_env("physics", TINY.num_envs, seed=0), TINY, seed=0)
    demos = demonstrations([trot])
    before = action_mse(model, demos.observations, demos.actions)
    stats = behaviour_clone(model, [trot], CloneConfig(steps=300, batch_size=256, log_std=-1.0, seed=0))
    assert stats.pairs + stats.val_pairs == len(demos.actions) and stats.episodes == trot.num_episodes
    assert stats.train_mse_before == pytest.approx(before, rel=0.2)
    assert stats.curve[-1][1] < 0.5 * stats.curve[0][1]  # the minibatch loss falls
    assert stats.train_mse_after < 0.25 * stats.train_mse_before
    assert stats.val_mse_after < 0.5 * stats.val_mse_before  # held-out episodes too
    assert torch.allclose(model.policy.log_std, torch.full((12,), -1.0))
    # the deterministic action SB3 applies is the cloned mean
    action, _ = model.predict(demos.observations[:64], deterministic=True)
    assert np.mean((action - demos.actions[:64]) ** 2) < 0.5 * before


def test_cloning_refuses_empty_data():
    model = make_ppo(make_env("physics", TINY.num_envs, seed=0), TINY, seed=0)
    with pytest.raises(ValueError, match="no usable"):
        behaviour_clone(model, [], CloneConfig(steps=1))


def test_mirror_keeps_the_better_side_and_adds_its_mirror_image(trot):
    from rwm_gym.rl.warm_start import Demonstrations, mirrored_better_half
    from rwm_gym.task.observation import observation_slices
    from rwm_gym.task.symmetry import action_mirror, observation_mirror

    spec = trot.spec()
    demos = demonstrations([trot])
    vy = observation_slices(spec)["command"].start + 1
    right = demos.observations[:, vy] < 0
    assert right.any() and (~right).any()
    reward = np.where(right, 1.0, 0.1).astype(np.float32)  # the demonstrator tracks right-hand commands better
    mirrored = mirrored_better_half(Demonstrations(demos.observations, demos.actions, demos.episode, reward), spec)
    n = int(right.sum())
    assert len(mirrored.actions) == 2 * n
    assert np.array_equal(mirrored.observations[:n], demos.observations[right])
    assert np.array_equal(mirrored.observations[n:], observation_mirror(spec)(demos.observations[right]))
    assert np.array_equal(mirrored.actions[n:], action_mirror(spec)(demos.actions[right]))
    assert (mirrored.observations[n:, vy] > 0).all()  # the images are left-hand commands
    assert not set(mirrored.episode[:n]) & set(mirrored.episode[n:])  # an image is an episode of its own
    # the other side wins when it tracks better
    flipped = mirrored_better_half(Demonstrations(demos.observations, demos.actions, demos.episode, 1 - reward), spec)
    assert np.array_equal(flipped.observations[: int((~right).sum())], demos.observations[~right])


def test_mirrored_cloning_fits_both_sides(trot):
    model = make_ppo(make_env("physics", TINY.num_envs, seed=0), TINY, seed=0)
    stats = behaviour_clone(model, [trot], CloneConfig(steps=300, batch_size=256, mirror=True, seed=0))
    assert stats.train_mse_after < 0.5 * stats.train_mse_before
