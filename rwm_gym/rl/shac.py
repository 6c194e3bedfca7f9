"""SHAC in imagination: first-order policy optimisation through the world model.

Short-Horizon Actor-Critic (Xu et al., ICLR 2022) in a learned simulator: the actor's loss is the negative discounted
return of a short imagined rollout (`SHACConfig.horizon` steps) plus the critic's value where it stops, and its
gradient flows back through the reward (`rwm_gym.task.reward_torch`), the world model's predicted states and the
actions that produced them; the critic learns TD(lambda) targets of the same rollouts. Where PPO needs millions of
samples to estimate a gradient, one backward pass gives it. Where the model is wrong, the gradient is wrong too
(the RWM paper reports SHAC through its model failing for that reason), so every update logs the actor's gradient
norm beside its return: a policy that exploits the model shows as an imagined return that rises while the physics
score does not (`benchmarks/time_to_walk.py` scores its snapshots in physics).

The policy is an SB3 `ActorCriticPolicy` of `rwm_gym.rl.ppo`'s layout (scaled observation, separate actor and critic
MLPs, Gaussian actions), trained by this module's own optimisers and saved as an ordinary SB3 PPO zip, so
`rwm-gym score`, `PPO.load` and PPO fine-tuning read it like any other policy.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import torch

from rwm_gym.imagination.core import ImaginedCore, tilt_degrees
from rwm_gym.options import check_ranges, option
from rwm_gym.task.commands import resample_period, sample_commands
from rwm_gym.task.observation import observation_parts
from rwm_gym.task.reward_torch import FeetAirTime, velocity_tracking_reward


@dataclass(frozen=True)
class SHACConfig:
    """SHAC's settings (`rwm-gym shac` generates its flags from these fields)."""

    num_envs: int = option(1024, ge=1)
    """Imagined robots stepped together; one update sees num_envs x horizon steps."""
    horizon: int = option(16, ge=1)
    """Imagined steps the actor's gradient flows back through (0.32 s at 50 Hz)."""
    actor_lr: float = option(1e-3, gt=0)
    """Adam learning rate of the actor."""
    critic_lr: float = option(1e-3, gt=0)
    """Adam learning rate of the critic."""
    gamma: float = option(0.99, ge=0, le=1)
    """Discount per policy step."""
    gae_lambda: float = option(0.95, ge=0, le=1)
    """lambda of the critic's TD(lambda) targets."""
    critic_iterations: int = option(8, ge=1)
    """Passes of the critic over each rollout."""
    critic_minibatches: int = option(4, ge=1)
    """Minibatches per critic pass."""
    target_critic_alpha: float = option(0.2, ge=0, lt=1)
    """Share of the old weights the target critic keeps at each update (0: it is the critic)."""
    max_grad_norm: float = option(1.0, gt=0)
    """Global gradient-norm clip of the actor and of the critic."""
    net_arch: tuple[int, ...] = option((128, 128, 128), ge=1)
    """Hidden layers of the actor and of the (separate) critic."""
    activation: str = "elu"
    """Activation of both MLPs: elu, tanh or relu."""
    log_std_init: float = option(-1.0, finite=True)
    """Log std of the Gaussian exploration noise the rollouts sample actions with (the reparameterised sample keeps
    the gradient); it is learned with the actor."""
    positive_reward_only: bool = True
    """Clip each step's reward at 0 from below, as the PPO recipe does (no gradient through the clipped steps)."""

    def __post_init__(self) -> None:
        check_ranges(self)

    def ppo_config(self):
        """The `PPOConfig` whose policy layout this learner trains (what `make_ppo` builds and saves)."""
        from rwm_gym.rl.ppo import PPOConfig

        return PPOConfig(
            num_envs=self.num_envs,
            n_steps=self.horizon,
            num_minibatches=1,
            net_arch=self.net_arch,
            activation=self.activation,
            log_std_init=self.log_std_init,
            positive_reward_only=self.positive_reward_only,
        )


class DifferentiableImagination:
    """The imagined task of an `ImaginedCore` on tensors, stepped with autograd.

    The core serves restarts (real history windows, their warm-up, fresh commands) and its options; steps run here,
    so the reward's gradient reaches the actions through the predicted states. Implements the time limit, the model's
    termination head, `fall_tilt`, `torque_halt` and the divergence guard; the uncertainty penalty and halt (which
    need every ensemble head on every step) are refused.
    """

    def __init__(self, core: ImaginedCore):
        options = core.options
        if options.acts_on_disagreement or options.sample_predictions or options.push_interval_s > 0:
            raise ValueError(
                "SHAC steps each env with its own head's mean: the uncertainty penalty and halt, "
                "sampled predictions and pushes are not implemented for it"
            )
        if core.spec.extra.get("dm_control") is not None or "command" not in core.spec.observation.groups:
            raise ValueError(f"SHAC here trains the velocity-tracking task, not {core.spec.name}")
        self.core, self.spec, self.norm = core, core.spec, core.norm
        self.model = core.model
        self.model.set_disagreement(False)
        self.device, n = core.device, core.num_envs
        self.period = resample_period(self.spec.command, self.spec.policy_dt)
        self.air = FeetAirTime(n, self.spec.foot_dim, self.device)
        self.steps = torch.zeros(n, dtype=torch.long, device=self.device)
        self.state = torch.zeros((n, self.spec.state_dim), device=self.device)
        self.last_action = torch.zeros((n, self.spec.action_dim), device=self.device)
        self.command = torch.zeros((n, len(self.spec.command.names)), device=self.device)
        self.hidden = tuple(h.clone() for h in core.hidden)
        self.effort_limit = torch.as_tensor(
            self.spec.actuator.per_joint("effort_limit"), dtype=torch.float32, device=self.device
        )

    def reset(self, ids: np.ndarray, seeds: list[int | None] | None = None) -> None:
        """Restart envs `ids` from real windows (the core's draw and warm-up); other envs keep their graph."""
        if len(ids) == 0:
            return
        self.core.reset(ids, seeds)
        index = torch.as_tensor(ids, device=self.device)

        def put(tensor: torch.Tensor, rows) -> torch.Tensor:
            return tensor.index_put((index,), torch.as_tensor(rows, dtype=tensor.dtype, device=self.device).clone())

        self.state = put(self.state, self.core.state[ids])
        self.last_action = put(self.last_action, self.core.last_action[ids])
        self.command = put(self.command, self.core.command[ids])
        self.hidden = tuple(put(h, c[index]) for h, c in zip(self.hidden, self.core.hidden, strict=True))
        self.steps[index] = torch.as_tensor(self.core.steps[ids], device=self.device)
        self.air.reset(index)

    def detach(self) -> None:
        """Cut the graph: the next update's gradient starts here."""
        self.state, self.last_action = self.state.detach(), self.last_action.detach()
        self.hidden = tuple(h.detach() for h in self.hidden)
        self.air.air_time = self.air.air_time.detach()

    def observe(self) -> torch.Tensor:
        """(N, O) observation, as `rwm_gym.task.observation.build_observation` builds it (no noise), differentiable."""
        return torch.cat(observation_parts(self.spec, self.state, self.command, self.last_action), dim=1)

    def step(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every env one step with autograd: reward (N,), terminated (N,) and truncated (N,) bool."""
        options = self.core.options
        x = self.norm.normalize_state(self.state)
        member = self.core.member if self.core.ensemble_size > 1 else None
        self.hidden, p = self.model.step(self.hidden, x, action, member)
        next_norm = p.state_mean
        diverged = (~torch.isfinite(next_norm).all(dim=1)) | (next_norm.abs() > options.divergence_bound).any(dim=1)
        next_norm = torch.where(diverged[:, None], x, next_norm)
        next_state = self.norm.denormalize_state(next_norm)
        contact = p.contact_logits > 0
        reward, _ = velocity_tracking_reward(
            self.spec, self.air, next_state, self.state, contact, self.command, action, self.last_action
        )
        terminated = diverged | (p.termination_logit > 0)
        if options.fall_tilt > 0:
            gravity = next_state[:, self.spec.state_slices["projected_gravity"]].detach().cpu().numpy()
            terminated |= torch.as_tensor(tilt_degrees(gravity) > options.fall_tilt, device=self.device)
        if options.torque_halt > 0:
            torque = next_state[:, self.spec.state_slices["joint_torque"]].detach().abs()
            terminated |= (torque >= options.torque_halt * self.effort_limit).any(dim=1)
        reward = torch.where(diverged, torch.zeros_like(reward), reward)
        self.state, self.last_action = next_state, action
        self.steps = self.steps + 1
        truncated = (self.steps >= self.core.episode_steps) & ~terminated
        self._resample_commands()
        return reward, terminated, truncated

    def _resample_commands(self) -> None:
        if not self.core.options.resample_commands:
            return
        due = np.flatnonzero((self.steps % self.period == 0).cpu().numpy())
        if len(due):
            fresh = sample_commands(self.spec.command, [self.core.rngs[i] for i in due])
            self.command = self.command.index_put(
                (torch.as_tensor(due, device=self.device),), torch.as_tensor(fresh, device=self.device)
            )


@dataclass
class UpdateStats:
    """One SHAC update."""

    timesteps: int
    """Imagined steps so far."""
    imagined_return: float
    """Mean per-env discounted return of the update's rollout with the critic's bootstrap (what the actor ascends)."""
    mean_step_reward: float
    actor_grad_norm: float
    """Norm of the actor's gradient before clipping: spikes mark where the model's gradient breaks."""
    critic_loss: float
    episodes_ended: int
    fraction_terminated: float
    """Share of env-steps that ended in a termination (a predicted fall, tilt, torque halt or divergence)."""
    action_std: float


class SHAC:
    """The learner: `learn()` runs updates on a `DifferentiableImagination` and trains `policy` in place."""

    def __init__(self, imagination: DifferentiableImagination, policy, config: SHACConfig, seed: int = 0):
        """policy: an SB3 `ActorCriticPolicy` of `config.ppo_config()`'s layout (`make_ppo(...).policy`)."""
        self.imagination, self.policy, self.config = imagination, policy, config
        self.generator = torch.Generator(device=imagination.device).manual_seed(seed)
        actor = [*policy.mlp_extractor.policy_net.parameters(), *policy.action_net.parameters(), policy.log_std]
        self.critic_modules = torch.nn.ModuleList([policy.mlp_extractor.value_net, policy.value_net])
        self.actor_optimizer = torch.optim.Adam(actor, lr=config.actor_lr, betas=(0.7, 0.95))
        self.critic_optimizer = torch.optim.Adam(
            self.critic_modules.parameters(), lr=config.critic_lr, betas=(0.7, 0.95)
        )
        self.actor_parameters = actor
        self.target_critic = copy.deepcopy(self.critic_modules).requires_grad_(False)
        self.timesteps = 0

    def _features(self, obs: torch.Tensor) -> torch.Tensor:
        return self.policy.features_extractor(obs)

    def _value(self, obs: torch.Tensor, modules: torch.nn.ModuleList) -> torch.Tensor:
        return modules[1](modules[0](self._features(obs))).squeeze(-1)

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        """A reparameterised Gaussian sample, clipped to the action box (the env's own clip)."""
        mean = self.policy.action_net(self.policy.mlp_extractor.forward_actor(self._features(obs)))
        noise = torch.randn(mean.shape, generator=self.generator, device=mean.device)
        return (mean + self.policy.log_std.exp() * noise).clamp(-1.0, 1.0)

    def update(self) -> UpdateStats:
        """One actor step through a `horizon`-step imagined rollout, then the critic's."""
        c, imagination = self.config, self.imagination
        n = imagination.core.num_envs
        imagination.detach()
        discount = torch.ones(n, device=imagination.device)
        objective = torch.zeros(n, device=imagination.device)
        observations, rewards, next_values, terminated_flags, done_flags = [], [], [], [], []
        ended = terminated_count = 0
        for t in range(c.horizon):
            obs = imagination.observe()
            reward, terminated, truncated = imagination.step(self.act(obs))
            if c.positive_reward_only:
                reward = reward.clamp(min=0.0)
            done = terminated | truncated
            last = t == c.horizon - 1
            bootstrap = (truncated | (~done if last else torch.zeros_like(done))).float()
            value_next = self._value(imagination.observe(), self.target_critic)  # the gradient reaches the state
            objective = objective + discount * (reward + c.gamma * bootstrap * value_next)
            discount = torch.where(done, torch.ones_like(discount), discount * c.gamma)
            observations.append(obs.detach())
            rewards.append(reward.detach())
            next_values.append(value_next.detach())
            terminated_flags.append(terminated)
            done_flags.append(done)
            finished = np.flatnonzero(done.cpu().numpy())
            ended += len(finished)
            terminated_count += int(terminated.sum())
            imagination.reset(finished)
        loss = -objective.mean() / c.horizon
        self.actor_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.actor_parameters, c.max_grad_norm)
        self.actor_optimizer.step()
        critic_loss = self._train_critic(
            torch.stack(observations),
            torch.stack(rewards),
            torch.stack(next_values),
            torch.stack(terminated_flags),
            torch.stack(done_flags),
        )
        self.timesteps += n * c.horizon
        return UpdateStats(
            self.timesteps,
            float(objective.mean().detach()),
            float(torch.stack(rewards).mean()),
            float(grad_norm),
            critic_loss,
            ended,
            terminated_count / (n * c.horizon),
            float(self.policy.log_std.detach().exp().mean()),
        )

    def _train_critic(self, obs, rewards, next_values, terminated, done) -> float:
        """Fit V to TD(lambda) targets of the rollout (T, N); the target critic follows softly."""
        c = self.config
        targets = torch.zeros_like(rewards)
        following = next_values[-1]
        for t in reversed(range(c.horizon)):
            alive = (~terminated[t]).float()
            blend = (
                next_values[t]
                if t == c.horizon - 1
                else torch.where(
                    done[t], next_values[t], (1 - c.gae_lambda) * next_values[t] + c.gae_lambda * following
                )
            )
            targets[t] = rewards[t] + c.gamma * alive * blend
            following = targets[t]
        flat_obs, flat_targets = obs.reshape(-1, obs.shape[-1]), targets.reshape(-1)
        size = len(flat_targets) // c.critic_minibatches
        total = 0.0
        for _ in range(c.critic_iterations):
            order = torch.randperm(len(flat_targets), generator=self.generator, device=flat_obs.device)
            for k in range(c.critic_minibatches):
                rows = order[k * size : (k + 1) * size]
                loss = (self._value(flat_obs[rows], self.critic_modules) - flat_targets[rows]).square().mean()
                self.critic_optimizer.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(self.critic_modules.parameters(), c.max_grad_norm)
                self.critic_optimizer.step()
                total += loss.item()
        with torch.no_grad():
            for target, source in zip(self.target_critic.parameters(), self.critic_modules.parameters(), strict=True):
                target.mul_(c.target_critic_alpha).add_((1 - c.target_critic_alpha) * source)
        return total / (c.critic_iterations * c.critic_minibatches)

    def state_dict(self) -> dict:
        """Everything a resumed run needs besides the policy's own weights."""
        return {
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "target_critic": self.target_critic.state_dict(),
            "timesteps": self.timesteps,
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.target_critic.load_state_dict(state["target_critic"])
        self.timesteps = int(state["timesteps"])
        self.generator.set_state(state["generator"])
