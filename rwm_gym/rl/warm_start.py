"""Behaviour cloning of logged demonstrations as the warm start of a PPO actor (`rwm-gym ppo --bc-data`).

PPO from scratch does not find a walk within the few million imagined steps a small CPU affords; the scripted trot the
world model was trained on (`rwm_gym.policies.gait`) does walk. We regress the SB3 policy's mean action onto the logged
actions (MSE, Adam) through the policy's own forward path (the fixed observation scaling of
`rwm_gym.rl.ppo.ScaledObservation`, `mlp_extractor.policy_net`, `action_net`), then lower the action std so
PPO's first rollouts stay near the walk. PPO then fine-tunes the cloned actor in imagination.

Pairs follow the dataset layout (`rwm_gym.data.dataset`): action[t] is applied in state[t]; the observation of row t is
`build_observation(spec, state[t], command[t], action[t-1])` with a zero last action at an episode's first row. The last
row of an episode has no action and is left out, and so are the `drop_before_fall` rows before a terminal state: they
show the demonstrator losing its balance, which the clone should not learn.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from stable_baselines3 import PPO

from rwm_gym.data.dataset import Dataset
from rwm_gym.spec import TaskSpec
from rwm_gym.task.observation import build_observation

DEMOS_FILE = "anymal_d_demos.h5"
"""The shipped demonstrations in `assets/checkpoints/`: 64 episodes (at most 250 rows each) of the scripted trot with
action noise 0.1, cut from the default checkpoint's training data by `write_demonstrations` (seed 0)."""


@dataclass(frozen=True)
class CloneConfig:
    """Behaviour-cloning settings."""

    steps: int = 4000
    """Adam steps (minibatches)."""
    batch_size: int = 512
    """(observation, action) pairs per step."""
    learning_rate: float = 1e-3
    """Adam learning rate, decayed linearly to 0 over `steps`."""
    log_std: float = -1.0
    """Log std of every action dimension after cloning (-1: std 0.37), so PPO explores near the clone."""
    drop_before_fall: int = 50
    """Rows (1 s at 50 Hz) before a terminal state that are not cloned."""
    last_action_noise: float = 0.0
    """Std of Gaussian noise added to the last-action input while cloning, so the clone does not merely copy its
    previous action (the copycat shortcut of cloning from action histories)."""
    observation_noise: float = 0.0
    """Scale of the spec's uniform observation noise added to the other inputs while cloning (0: none, 1: the
    spec's)."""
    mirror: bool = False
    """Clone the half of the commands the demonstrator tracks better and that half's left-right mirror image (the
    spec's `[symmetry]`) in place of all pairs: a demonstrator that walks to one side only teaches both sides."""
    val_fraction: float = 0.1
    """Episodes held out to report the validation MSE."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.steps < 1 or self.batch_size < 1 or not 0.0 <= self.val_fraction < 1.0:
            raise ValueError(
                f"CloneConfig: steps {self.steps} and batch_size {self.batch_size} must be >= 1, "
                f"val_fraction {self.val_fraction} in [0, 1)"
            )


@dataclass
class CloneStats:
    """What `behaviour_clone` did; MSEs are per action entry, actions in [-1, 1]."""

    pairs: int
    """Training pairs."""
    val_pairs: int
    episodes: int
    wall_s: float
    train_mse_before: float
    train_mse_after: float
    val_mse_before: float | None
    val_mse_after: float | None
    curve: list[tuple[int, float]] = field(default_factory=list)
    """(step, minibatch MSE averaged over the last stretch)."""

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Demonstrations:
    """(observation, action) pairs with the episode each came from."""

    observations: np.ndarray
    """(P, O) float32, raw (unscaled) policy observations."""
    actions: np.ndarray
    """(P, A) float32 in [-1, 1]."""
    episode: np.ndarray
    """(P,) int64, a running episode index over all datasets."""
    reward: np.ndarray
    """(P,) float32, the step reward of each pair."""


def demonstrations(datasets: Sequence[Dataset | str | os.PathLike], *, drop_before_fall: int = 50) -> Demonstrations:
    """All (observation, action) pairs of `datasets` (see the module docstring for which rows are used)."""
    obs, act, eps, rew, offset = [], [], [], [], 0
    for source in datasets:
        ds = source if isinstance(source, Dataset) else Dataset.load(source)
        spec = ds.spec()
        state, command, action = ds["state"], ds["command"], ds["action"]
        terminated = ds["terminated"]
        last = np.zeros_like(action)
        last[1:] = action[:-1]
        keep = np.zeros(len(state), dtype=bool)
        episode = np.zeros(len(state), dtype=np.int64)
        for i, (start, length) in enumerate(zip(ds.episode_starts, ds.episode_lengths)):
            end = start + length - 1  # the last row has no transition
            if terminated[start + length - 1]:
                end -= drop_before_fall
            keep[start : max(end, start)] = True
            last[start] = 0.0
            episode[start : start + length] = offset + i
        offset += ds.num_episodes
        obs.append(build_observation(spec, state[keep], command[keep], last[keep]))
        act.append(action[keep].astype(np.float32))
        eps.append(episode[keep])
        rew.append(ds["reward"][keep].astype(np.float32))
    if not obs or sum(len(a) for a in act) == 0:
        names = ", ".join(str(d if not isinstance(d, Dataset) else d.path) for d in datasets) or "(none)"
        raise ValueError(f"behaviour cloning: no usable (observation, action) pairs in {names}")
    return Demonstrations(np.concatenate(obs), np.concatenate(act), np.concatenate(eps), np.concatenate(rew))


def mirrored_better_half(demos: Demonstrations, spec: TaskSpec) -> Demonstrations:
    """The pairs on the side of the commands with the higher mean reward, and their mirror images.

    The sides are the signs of the first command the mirror negates (the lateral velocity of a legged task); the
    image of a pair is the mirrored observation and action, in an episode of its own (index offset past the last)."""
    from rwm_gym.task.observation import observation_slices
    from rwm_gym.task.symmetry import action_mirror, observation_mirror, symmetry_table

    signs = symmetry_table(spec).signs.get("command")
    if signs is None or min(signs) > 0:
        raise ValueError(f"behaviour cloning --bc-mirror: task spec {spec.name} mirrors no command")
    column = observation_slices(spec)["command"].start + int(np.argmin(signs))
    negative = demos.observations[:, column] < 0.0
    sides = [side for side in (negative, ~negative) if side.any()]
    keep = max(sides, key=lambda side: float(demos.reward[side].mean()))
    offset = int(demos.episode.max()) + 1
    return Demonstrations(
        np.concatenate([demos.observations[keep], observation_mirror(spec)(demos.observations[keep])]),
        np.concatenate([demos.actions[keep], action_mirror(spec)(demos.actions[keep])]),
        np.concatenate([demos.episode[keep], demos.episode[keep] + offset]),
        np.concatenate([demos.reward[keep], demos.reward[keep]]),
    )


def mean_action(model: PPO, observations):
    """The policy's deterministic (mean) action for raw observations (a torch tensor (N, O)): scaling, MLP, head."""
    policy = model.policy
    latent = policy.mlp_extractor.forward_actor(policy.extract_features(observations, policy.pi_features_extractor))
    return policy.action_net(latent)


def action_mse(model: PPO, observations: np.ndarray, actions: np.ndarray) -> float:
    """Mean squared error per action entry of the policy's mean action (clipped to [-1, 1] as it is applied)."""
    import torch

    with torch.no_grad():
        pred = mean_action(model, torch.as_tensor(observations, device=model.device)).clamp(-1.0, 1.0)
        return float(((pred - torch.as_tensor(actions, device=model.device)) ** 2).mean())


def _input_noise(dataset: Dataset | str | os.PathLike, config: CloneConfig) -> np.ndarray:
    """(O,) std of the Gaussian noise on each observation entry while cloning."""
    from rwm_gym.task.observation import observation_slices

    ds = dataset if isinstance(dataset, Dataset) else Dataset.load(dataset)
    spec = ds.spec()
    std = np.zeros(sum(s.stop - s.start for s in observation_slices(spec).values()), dtype=np.float32)
    for name, where in observation_slices(spec).items():
        if name == "last_action":
            std[where] = config.last_action_noise
        else:  # uniform noise of half-width w has std w / sqrt(3)
            std[where] = config.observation_noise * spec.observation.noise.get(name, 0.0) / np.sqrt(3.0)
    return std


def behaviour_clone(
    model: PPO,
    datasets: Sequence[Dataset | str | os.PathLike],
    config: CloneConfig = CloneConfig(),
    *,
    progress: bool = False,
) -> CloneStats:
    """Fit `model`'s actor mean to the demonstrations in `datasets` in place, then set its log std to config.log_std.

    The critic is left as it is. A fraction `val_fraction` of the episodes is held out (when there are at least two).
    """
    import torch
    from tqdm import tqdm

    started = time.monotonic()
    datasets = [d if isinstance(d, Dataset) else Dataset.load(d) for d in datasets]  # each file read once
    demos = demonstrations(datasets, drop_before_fall=config.drop_before_fall)
    if config.mirror:
        demos = mirrored_better_half(demos, datasets[0].spec())
    rng = np.random.default_rng(config.seed)
    episodes = np.unique(demos.episode)
    n_val = int(round(config.val_fraction * len(episodes))) if len(episodes) > 1 else 0
    val_eps = rng.permutation(episodes)[:n_val]
    val = np.isin(demos.episode, val_eps)
    obs_tr, act_tr = demos.observations[~val], demos.actions[~val]
    obs_va, act_va = demos.observations[val], demos.actions[val]

    policy = model.policy
    params = [*policy.mlp_extractor.policy_net.parameters(), *policy.action_net.parameters()]
    optimizer = torch.optim.Adam(params, lr=config.learning_rate)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda k: 1.0 - k / config.steps)
    noise = torch.as_tensor(_input_noise(datasets[0], config), device=model.device)
    x = torch.as_tensor(obs_tr, device=model.device)
    y = torch.as_tensor(act_tr, device=model.device)
    generator = torch.Generator().manual_seed(config.seed)
    before = action_mse(model, obs_tr, act_tr), (action_mse(model, obs_va, act_va) if len(obs_va) else None)
    curve, running, every = [], 0.0, max(config.steps // 20, 1)
    policy.set_training_mode(True)
    for step in tqdm(range(1, config.steps + 1), desc="behaviour cloning", disable=not progress, dynamic_ncols=True):
        idx = torch.randint(len(x), (config.batch_size,), generator=generator).to(model.device)
        inputs = x[idx] + noise * torch.randn(len(idx), x.shape[1], generator=generator).to(model.device)
        loss = ((mean_action(model, inputs) - y[idx]) ** 2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
        running += loss.item()
        if step % every == 0:
            curve.append((step, running / every))
            running = 0.0
    policy.set_training_mode(False)
    with torch.no_grad():
        policy.log_std.fill_(config.log_std)
    return CloneStats(
        pairs=len(obs_tr),
        val_pairs=len(obs_va),
        episodes=len(episodes),
        wall_s=time.monotonic() - started,
        train_mse_before=before[0],
        train_mse_after=action_mse(model, obs_tr, act_tr),
        val_mse_before=before[1],
        val_mse_after=action_mse(model, obs_va, act_va) if len(obs_va) else None,
        curve=curve,
    )


def default_demonstrations() -> Path:
    """The shipped trot demonstrations (`DEMOS_FILE`), found in the package data (also after `pip install .`)."""
    from rwm_gym.resources import assets_dir

    return assets_dir() / "checkpoints" / DEMOS_FILE


def write_demonstrations(
    source: Dataset | str | os.PathLike, out: str | os.PathLike, *, episodes: int = 64, rows: int = 250, seed: int = 0
) -> Path:
    """A small demonstration file: `episodes` episodes of `source`, at most `rows` rows each, gzip-compressed.

    The same cut as the reset data (`make_reset_data`), then every field rewritten whole with gzip + shuffle, which
    halves the file (the writer's per-episode appends leave it fragmented). The result is an ordinary dataset.
    """
    import h5py

    from rwm_gym.imagination.reset_data import make_reset_data

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        cut = make_reset_data(source, Path(tmp) / "cut.h5", episodes=episodes, rows=rows, seed=seed)
        packed = Path(tmp) / "packed.h5"
        with h5py.File(cut, "r") as src, h5py.File(packed, "w") as dst:
            dst.attrs.update(dict(src.attrs))
            dst.create_dataset("episode_lengths", data=src["episode_lengths"][:])
            steps = dst.create_group("steps")
            for name, values in src["steps"].items():
                steps.create_dataset(name, data=values[:], compression="gzip", compression_opts=9, shuffle=True)
        Dataset.load(packed)  # refuse to ship a file the reader rejects
        os.replace(packed, out)
    return out
