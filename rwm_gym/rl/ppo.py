"""PPO in imagination (or in physics, the model-free baseline): settings, env and learner (`rwm-gym ppo` is
`rwm_gym.commands.ppo`).

Stable-Baselines3's PPO with RWM's settings (`PPOConfig`): actor and critic 128-128-128 ELU, initial action std 1,
clip 0.2, 5 epochs of 4 minibatches, lr 1e-3 adapted to a KL target of 0.01 (rsl_rl's rule), gamma 0.99, lambda 0.95,
entropy 0.005. The policy is saved as an ordinary SB3 zip (`PPO.load(path)` needs nothing else); the config, the
training statistics and the physics evaluation go beside it as JSON.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper

from rwm_gym.options import check_ranges, option
from rwm_gym.progress import BudgetBar, whole_rollouts
from rwm_gym.rl.policy_file import save_policy  # noqa: F401  (re-exported: callers save policies from here)
from rwm_gym.spec import TaskSpec

WHERE = ("imagination", "physics")


@dataclass(frozen=True)
class PPOConfig:
    """PPO hyperparameters (RWM's 'policy in imagination' figures, sized for a small CPU by default)."""

    num_envs: int = option(512, ge=1)
    """Envs stepped together; one rollout is num_envs x n_steps transitions."""
    n_steps: int = option(24, ge=1)
    """Steps per env per update."""
    net_arch: tuple[int, ...] = option((128, 128, 128), ge=1)
    """Hidden layers of the actor and of the (separate) critic."""
    activation: str = "elu"
    """Activation of both MLPs: elu, tanh or relu."""
    log_std_init: float = option(0.0, finite=True)
    """Initial log std of the Gaussian policy (0: std 1); with `use_sde`, of the exploration matrix's entries."""
    use_sde: bool = False
    """Generalised state-dependent exploration (gSDE, Raffin et al. 2021): the action noise is a random linear function
    of the actor's last hidden layer, held for `sde_sample_freq` steps, so it is smooth in time instead of white."""
    sde_sample_freq: int = option(-1, ge=-1)
    """Steps between fresh exploration matrices with `use_sde` (-1: once per rollout)."""
    clip_range: float = option(0.2, gt=0)
    """PPO ratio clip."""
    n_epochs: int = option(5, ge=1)
    """Passes over each rollout."""
    num_minibatches: int = option(4, ge=1)
    """Minibatches per pass (batch size = num_envs x n_steps / num_minibatches)."""
    learning_rate: float = option(1e-3, gt=0)
    """Initial Adam learning rate."""
    target_kl: float = option(0.01, ge=0)
    """KL target of the adaptive learning rate: /1.5 above 2x, x1.5 below 1/2 (0: constant learning rate)."""
    lr_anneal_fraction: float = option(0.0, ge=0, le=1)
    """Last fraction of a `--timesteps` budget over which the learning rate falls linearly from its adapted value to
    one rollout's share (KL adaptation stops there): the policy settles instead of wandering between snapshots
    (0: none)."""
    gamma: float = option(0.99, ge=0, le=1)
    """Discount per policy step."""
    gae_lambda: float = option(0.95, ge=0, le=1)
    """GAE lambda."""
    ent_coef: float = option(0.005, ge=0)
    """Entropy bonus weight."""
    vf_coef: float = option(1.0, ge=0)
    """Value-loss weight."""
    max_grad_norm: float = option(1.0, gt=0)
    """Global gradient-norm clip."""
    critic_warmup_steps: int = option(0, ge=0)
    """Env steps that train only the critic before the actor moves (for a warm-started actor; 0: none)."""
    positive_reward_only: bool = False
    """Clip each step's reward at 0 from below (legged_gym's only_positive_rewards): a young policy whose penalties
    outweigh its tracking reward is not paid to end its episodes early."""
    update_precision: str = "float32"
    """dtype of the products in PPO's update: float32, or bfloat16 (autocast around each update; the rollouts stay
    float32). The update is most of PPO's time at 1024 envs; bf16 runs it 1.5x faster on CPUs with AVX512-BF16 or
    AMX, but two seeds trained with it learned markedly slower than with float32 (docs/results/time-to-walk.md)."""
    symmetry: bool = False
    """Train on each sample and its left-right mirror image (the task spec's [symmetry] table): every minibatch
    doubles (rwm_gym.rl.mirror_buffer)."""

    def __post_init__(self) -> None:
        if self.update_precision not in UPDATE_PRECISIONS:
            raise ValueError(
                f"PPOConfig.update_precision {self.update_precision!r} unknown (choose from "
                f"{', '.join(UPDATE_PRECISIONS)})"
            )
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"PPOConfig.activation {self.activation!r} unknown (choose from {', '.join(ACTIVATIONS)})")
        check_ranges(self)
        if self.num_envs * self.n_steps < 2:
            raise ValueError("PPOConfig: a rollout of num_envs x n_steps must hold at least 2 transitions, got 1")
        if (self.num_envs * self.n_steps) % self.num_minibatches:
            raise ValueError(
                f"PPOConfig: num_envs x n_steps ({self.num_envs * self.n_steps}) is not divisible by "
                f"num_minibatches ({self.num_minibatches})"
            )

    def to_dict(self) -> dict:
        return asdict(self)


ACTIVATIONS = ("elu", "tanh", "relu")
UPDATE_PRECISIONS = ("float32", "bfloat16")


class UpdatePrecision(BaseCallback):
    """Runs SB3's update (`train`, called right after a rollout ends) under bf16 autocast, and the rollouts without:
    the autocast is entered at a rollout's end and left when the next rollout starts or training ends. The action and
    value heads stay float32, so that the update's probability ratios and values are not rounded to bf16."""

    def __init__(self, device: str):
        super().__init__()
        self.device_type = torch.device(device).type
        self.autocast = None

    def _on_training_start(self) -> None:
        for head in (self.model.policy.action_net, self.model.policy.value_net):
            head.forward = _float32_linear(head)  # on the instance: not in the saved policy, set again on resume

    def _on_rollout_end(self) -> None:
        self.autocast = torch.autocast(self.device_type, dtype=torch.bfloat16)
        self.autocast.__enter__()

    def _leave(self) -> None:
        if self.autocast is not None:
            self.autocast.__exit__(None, None, None)
            self.autocast = None

    def _on_rollout_start(self) -> None:
        self._leave()

    def _on_training_end(self) -> None:
        self._leave()

    def _on_step(self) -> bool:
        return True


def _float32_linear(layer: torch.nn.Linear):
    def forward(x: torch.Tensor) -> torch.Tensor:
        with torch.autocast(x.device.type, enabled=False):
            return torch.nn.functional.linear(x.float(), layer.weight, layer.bias)

    return forward


def update_callbacks(config: PPOConfig, model: PPO) -> tuple[BaseCallback, ...]:
    """The callbacks `config` asks of every `learn` call (bf16 updates)."""
    return (UpdatePrecision(str(model.device)),) if config.update_precision == "bfloat16" else ()


def observation_scale(spec: TaskSpec) -> tuple[list[float], list[float]]:
    """Fixed (mean, std) of every observation entry: the spec's state normalisation; commands and actions as they are.

    Raw observations mix m/s, rad and rad/s of very different spread; the policy sees them on a common scale.
    """
    mean, std = [], []
    groups = {g.name: g for g in spec.state}
    for name in spec.observation.groups:
        size = len(spec.command.names) if name == "command" else spec.action_dim if name == "last_action" else 0
        if name in groups:
            mean += list(groups[name].mean)
            std += list(groups[name].std)
        else:
            mean += [0.0] * size
            std += [1.0] * size
    return mean, std


class ScaledObservation(BaseFeaturesExtractor):
    """(obs - mean) / std with fixed, saved constants (part of the policy, so the SB3 zip stays self-contained), and
    the physics env id of the task the policy was made for (`task`), so the zip names its robot: a Go2 and an ANYmal
    D policy have the same sizes and scale."""

    def __init__(self, observation_space, mean: list[float], std: list[float], task: str | None = None):
        super().__init__(observation_space, observation_space.shape[0])
        self.register_buffer("mean", torch.tensor(mean, dtype=torch.float32))
        self.register_buffer("std", torch.tensor(std, dtype=torch.float32))
        self.task = task

    def forward(self, observations):
        return (observations - self.mean) / self.std


def trained_task(model: PPO) -> str | None:
    """The physics env id of the task a policy was made for (its `ScaledObservation`'s `task`); None for a policy
    that does not name one (made before policies did, or without the scale)."""
    return getattr(getattr(model.policy, "features_extractor", None), "task", None)


class PositiveReward(VecEnvWrapper):
    """Rewards clipped at 0 from below (`PPOConfig.positive_reward_only`); the clipped reward is what PPO sees."""

    def reset(self):
        return self.venv.reset()

    def step_wait(self):
        obs, reward, done, infos = self.venv.step_wait()
        return obs, np.maximum(reward, 0.0), done, infos


def make_ppo(env: VecEnv, config: PPOConfig, *, seed: int = 0, device: str = "cpu") -> PPO:
    """A fresh SB3 PPO on `env` with `config`'s settings; observations scaled by the env's task spec (ValueError
    for `symmetry` when the spec has no mirror)."""
    spec = env.get_attr("spec")[0]
    mean, std = observation_scale(spec)
    if config.symmetry:
        from rwm_gym.task.symmetry import action_mirror

        action_mirror(spec)  # ValueError (one line) before anything is built when the spec has no mirror
    if config.positive_reward_only:
        env = PositiveReward(env)

    activation = {"elu": torch.nn.ELU, "tanh": torch.nn.Tanh, "relu": torch.nn.ReLU}[config.activation]
    arch = list(config.net_arch)
    model = PPO(
        "MlpPolicy",
        env,
        learning_rate=config.learning_rate,
        n_steps=config.n_steps,
        batch_size=env.num_envs * config.n_steps // config.num_minibatches,
        n_epochs=config.n_epochs,
        gamma=config.gamma,
        gae_lambda=config.gae_lambda,
        clip_range=config.clip_range,
        ent_coef=config.ent_coef,
        vf_coef=config.vf_coef,
        max_grad_norm=config.max_grad_norm,
        use_sde=config.use_sde,
        sde_sample_freq=config.sde_sample_freq,
        seed=seed,
        device=device,
        verbose=0,
        policy_kwargs={
            "net_arch": {"pi": arch, "vf": arch},
            "activation_fn": activation,
            "log_std_init": config.log_std_init,
            "features_extractor_class": ScaledObservation,
            "features_extractor_kwargs": {"mean": mean, "std": std, "task": spec.physics_env_id},
        },
    )
    if config.symmetry:
        from rwm_gym.rl.mirror_buffer import use_mirrored_buffer

        use_mirrored_buffer(model, spec)
    return model


def load_ppo(path, env: VecEnv, config: PPOConfig, *, device: str = "cpu") -> PPO:
    """A saved PPO policy to continue training on `env` with `config`'s buffer (the mirrored one for `symmetry`)."""
    from rwm_gym.policy_zip import load_policy

    model = load_policy(path, env=env, device=device)  # runs no code from the file
    if config.symmetry:
        from rwm_gym.rl.mirror_buffer import use_mirrored_buffer

        use_mirrored_buffer(model, env.get_attr("spec")[0])
    return model


def start_from(model: PPO, path: str | os.PathLike) -> None:
    """Give `model` the network of the policy saved at `path` (actor, critic, action std and observation scale):
    fine-tuning with `model`'s own PPO settings. ValueError (one line) when the two networks differ in shape."""
    from rwm_gym.policy_zip import load_policy

    source = load_policy(path, device=str(model.device)).policy.state_dict()  # runs no code from the file
    target = model.policy.state_dict()
    mismatched = sorted(
        k for k in set(source) | set(target) if k not in source or k not in target or source[k].shape != target[k].shape
    )
    if mismatched:
        raise ValueError(
            f"{path}: its network does not fit this policy's ({', '.join(mismatched[:3])}"
            f"{' ...' if len(mismatched) > 3 else ''}); give the same --net-arch and task"
        )
    model.policy.load_state_dict(source)


def annealed_fraction(timesteps: int, end: int, anneal_steps: float, rollout: int) -> float:
    """Share of the learning rate left for the update after the rollout that ended at `timesteps`: 1 until the last
    `anneal_steps` of a budget that ends at `end`, then falling linearly to `rollout / anneal_steps` at the last
    update."""
    if anneal_steps <= 0:
        return 1.0
    return min(1.0, max(end - timesteps + rollout, rollout) / anneal_steps)


class _Progress(BaseCallback):
    """tqdm bar, wall-clock budget, rsl_rl's adaptive learning rate and its final anneal, one log row per rollout."""

    def __init__(
        self,
        total: int | None,
        minutes: float | None,
        target_kl: float,
        bar: bool,
        on_rollout=None,
        anneal_steps: float = 0.0,
    ):
        super().__init__()
        self.total, self.minutes, self.target_kl, self.show = total, minutes, target_kl, bar
        self.on_rollout, self.anneal_steps = on_rollout, anneal_steps
        self.log: list[dict] = []

    def _on_training_start(self) -> None:
        self.started = time.monotonic()
        self.start_steps = self.num_timesteps
        self.rollout = self.model.n_steps * self.training_env.num_envs
        steps = self.total and whole_rollouts(self.total, self.rollout)
        self.end = self.start_steps + (steps or 0)
        self.bar = BudgetBar(steps=steps, minutes=self.minutes, desc="ppo", unit_scale=True, disable=not self.show)
        self.running = np.zeros(self.training_env.num_envs)
        self.reward_sum, self.reward_count, self.finished = 0.0, 0, []

    def _on_step(self) -> bool:
        # the env's own rewards: SB3 adds value bootstraps at time limits into its buffer after this call
        rewards, dones = self.locals["rewards"], self.locals["dones"]
        self.reward_sum += float(rewards.sum())
        self.reward_count += rewards.size
        self.running += rewards
        self.finished += self.running[dones].tolist()
        self.running[dones] = 0.0
        seconds = time.monotonic() - self.started
        if self.bar.by_time:
            self.bar.show(self.num_timesteps - self.start_steps, seconds)
        return self.minutes is None or seconds < 60 * self.minutes

    def _on_rollout_end(self) -> None:
        kl = getattr(self.model.rollout_buffer, "original_kl", None)  # the mirrored buffer's: its original half
        if kl is None:
            kl = self.model.logger.name_to_value.get("train/approx_kl")  # previous update's (the logger dumps later)
        lr = previous = self.model.lr_schedule(1.0)
        share = annealed_fraction(self.num_timesteps, self.end, self.anneal_steps, self.rollout)
        if share < 1.0:  # scale the previous update's lr by the ratio of shares: resumes from the saved lr alone
            lr *= share / annealed_fraction(
                self.num_timesteps - self.rollout, self.end, self.anneal_steps, self.rollout
            )
        elif self.target_kl > 0 and kl is not None:
            if kl > 2.0 * self.target_kl:
                lr = max(1e-5, lr / 1.5)
            elif kl < self.target_kl / 2.0:
                lr = min(1e-2, lr * 1.5)
        if lr != previous:
            self.model.learning_rate = lr
            self.model._setup_lr_schedule()
        reward = self.reward_sum / max(self.reward_count, 1)
        returns = float(np.mean(self.finished)) if self.finished else None
        self.log.append(
            {
                "timesteps": int(self.num_timesteps),
                "wall_s": time.monotonic() - self.started,
                "mean_step_reward": reward,
                "episodes": len(self.finished),
                "mean_episode_return": returns,
                "lr": lr,
                "approx_kl": None if kl is None else float(kl),
                "std": float(self.model.policy.log_std.detach().exp().mean()),
            }
        )
        if self.on_rollout is not None:
            self.on_rollout(self.log[-1])
        self.reward_sum, self.reward_count, self.finished = 0.0, 0, []
        self.bar.show(
            self.num_timesteps - self.start_steps,
            time.monotonic() - self.started,
            reward=f"{reward:.4f}",
            lr=f"{lr:.1e}",
        )

    def _on_training_end(self) -> None:
        self.bar.close()


@dataclass
class TrainStats:
    """What one `learn` call did."""

    timesteps: int
    """Env steps taken (imagined or physics)."""
    wall_s: float
    steps_per_s: float
    log: list[dict] = field(default_factory=list)
    """Per rollout: timesteps, wall_s, mean_step_reward (the env's), episodes ended and their mean_episode_return, lr,
    approx_kl (of the update before the rollout), std (mean action std)."""


def learn(
    model: PPO,
    *,
    timesteps: int | None = None,
    minutes: float | None = None,
    target_kl: float = 0.01,
    progress: bool = True,
    callbacks: tuple[BaseCallback, ...] = (),
    on_rollout=None,
    anneal_steps: float = 0.0,
) -> TrainStats:
    """Continue training `model` on its env for `timesteps` more steps and/or `minutes` (whichever ends first).

    `callbacks` run after the progress bar's; `on_rollout(row)` receives each rollout's log row. Over the last
    `anneal_steps` env steps of `timesteps` the learning rate falls linearly (`annealed_fraction`) instead of adapting.
    """
    if not timesteps and not minutes:
        raise ValueError("set a budget: timesteps and/or minutes")
    if anneal_steps and not timesteps:
        raise ValueError("a learning-rate anneal needs a timesteps budget: it ends with it")
    total = int(timesteps) if timesteps else 10**12  # SB3 runs whole rollouts: the bar counts those
    callback = _Progress(total if timesteps else None, minutes, target_kl, progress, on_rollout, anneal_steps)
    before, started = model.num_timesteps, time.monotonic()
    model.learn(total, callback=CallbackList([callback, *callbacks]), reset_num_timesteps=False, progress_bar=False)
    wall = time.monotonic() - started
    done = model.num_timesteps - before
    return TrainStats(done, wall, done / max(wall, 1e-9), callback.log)


def warm_up_critic(model: PPO, timesteps: int, *, progress: bool = True) -> TrainStats:
    """Train only the value function for `timesteps` env steps: actor frozen, learning rate constant.

    A cloned actor (`rwm_gym.rl.warm_start`) beside a freshly initialised critic gets advantages that are
    noise, and PPO's first updates would pull it off the demonstrations before anything is learnt. Fitting the clone's
    value first makes those updates point somewhere.
    """
    policy = model.policy
    actor = [*policy.mlp_extractor.policy_net.parameters(), *policy.action_net.parameters(), policy.log_std]
    trainable = [p.requires_grad for p in actor]
    for p in actor:
        p.requires_grad_(False)
    try:
        return learn(model, timesteps=timesteps, target_kl=0.0, progress=progress)
    finally:
        for p, flag in zip(actor, trainable):
            p.requires_grad_(flag)


def make_env(
    where: str,
    num_envs: int,
    *,
    checkpoint: str | os.PathLike | None = None,
    device: str = "cpu",
    seed: int = 0,
    env_kwargs: dict | None = None,
    physics_env: str | os.PathLike | None = None,
) -> VecEnv:
    """The SB3 VecEnv to train in: the imagined env on `checkpoint` (None: the shipped one) or batched physics of
    `physics_env` (a physics id, spec name or path; None: the shipped legged task), MuJoCo or dm_control."""
    if where == "imagination":
        from rwm_gym.vector.sb3_vec_env import ImaginedSB3VecEnv

        env = ImaginedSB3VecEnv(checkpoint=checkpoint, num_envs=num_envs, device=device, **(env_kwargs or {}))
    elif where == "physics":
        env = _physics_env(physics_env, num_envs, env_kwargs or {})
    else:
        raise ValueError(f"--in {where!r} unknown (choose from {', '.join(WHERE)})")
    env.seed(seed)
    return env


def _physics_env(physics_env: str | os.PathLike | None, num_envs: int, env_kwargs: dict) -> VecEnv:
    """Batched physics as an SB3 VecEnv: a dm_control task's `DMCSB3VecEnv` or the legged task's MuJoCo one."""
    from rwm_gym.vector.sb3_vec_env import DMCSB3VecEnv, LocomotionSB3VecEnv

    if physics_env is None:
        return LocomotionSB3VecEnv(num_envs=num_envs, **env_kwargs)
    from rwm_gym.registration import resolve_spec, simulator_of

    spec = resolve_spec(physics_env)
    if simulator_of(spec) == "dm_control":
        if env_kwargs:
            raise ValueError(
                f"{spec.name} is a dm_control task: physics options ({', '.join(env_kwargs)}) do not apply"
            )
        return DMCSB3VecEnv(num_envs=num_envs, spec=spec)
    return LocomotionSB3VecEnv(num_envs=num_envs, spec=spec, **env_kwargs)
