"""A Dreamer-style actor-critic in imagination: lambda-returns through the world model's imagined rollouts.

DreamerV3 (Hafner et al., 2023) learns its behaviour entirely inside its world model: from real start states it
imagines `horizon` steps with the actor, computes lambda-returns bootstrapped by a critic, and trains the actor to
raise them and the critic to predict them. Here the imagined rollout is the package's differentiable imagination
(`rwm_gym.rl.shac.DifferentiableImagination`: the RWM GRU world model, the torch reward of
`rwm_gym.task.reward_torch`, the task's terminations), restarted from real history windows as PPO's is. What is
DreamerV3's and what differs:

- lambda-returns R_t = r_t + gamma c_t ((1 - lambda) v(s_t+1) + lambda R_t+1) over every imagined step, bootstrapped by
  a slow critic (an exponential moving average of the critic's weights, `target_critic_decay`); the critic regresses
  them (squared error; DreamerV3's two-hot symlog critic is not used: the task's returns are small and bounded);
- the actor's loss is the return normalised by S = max(1, P95 - P5) of the returns (an EMA of the percentile range,
  DreamerV3's return normalisation), minus `entropy_coef` x the policy's entropy;
- the actor's gradient is backpropagation through the dynamics by default (`actor_gradient="dynamics"`, DreamerV3's
  choice for continuous actions: the model is differentiable and the 12 joint targets are continuous, so one backward
  pass gives a low-variance gradient); `"reinforce"` (DreamerV3's estimator for discrete actions) weighs the
  log-probability of each imagined action by its normalised advantage, with no gradient through the model, for
  comparison where the model's gradients are poor;
- unlike SHAC (`rwm_gym.rl.shac`), which ascends one discounted return per rollout, every step's lambda-return is an
  objective and the critic bootstraps every one of them.

The policy is the SB3 `ActorCriticPolicy` layout of `rwm_gym.rl.ppo` (as SHAC's), saved as an ordinary PPO zip that
`rwm-gym score` and PPO fine-tuning read. Each update reports the actor's gradient norm, the imagined return and the
return scale, so a policy that exploits the model shows as an imagined return rising while the physics score does not.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import torch

from rwm_gym.options import check_ranges, option
from rwm_gym.rl.shac import DifferentiableImagination

ACTOR_GRADIENTS = ("dynamics", "reinforce")
"""How the actor's gradient is estimated: backpropagation through the model, or the score-function estimator."""


@dataclass(frozen=True)
class DreamerConfig:
    """Settings of the Dreamer-style learner (`rwm-gym dreamer` generates its flags from these fields)."""

    num_envs: int = option(1024, ge=1)
    """Imagined robots stepped together; one update sees num_envs x horizon imagined steps."""
    horizon: int = option(16, ge=1)
    """Imagined steps per update, the lambda-returns' horizon (DreamerV3: 15; 0.32 s at 50 Hz)."""
    actor_lr: float = option(3e-4, gt=0)
    """Adam learning rate of the actor."""
    critic_lr: float = option(3e-4, gt=0)
    """Adam learning rate of the critic."""
    gamma: float = option(0.99, gt=0, le=1)
    """Discount per policy step."""
    return_lambda: float = option(0.95, ge=0, le=1)
    """lambda of the lambda-returns (0: one-step TD targets, 1: Monte-Carlo returns to the horizon)."""
    entropy_coef: float = option(3e-4, ge=0)
    """Weight of the policy's entropy in the actor's loss (DreamerV3's eta, on normalised returns)."""
    return_decay: float = option(0.99, ge=0, lt=1)
    """EMA decay of the returns' percentile range S that normalises the actor's objective."""
    target_critic_decay: float = option(0.98, ge=0, lt=1)
    """EMA decay of the slow critic that bootstraps the lambda-returns (0: it is the critic)."""
    critic_iterations: int = option(4, ge=1)
    """Passes of the critic over each rollout."""
    critic_minibatches: int = option(4, ge=1)
    """Minibatches per critic pass."""
    actor_gradient: str = option("dynamics", choices=ACTOR_GRADIENTS)
    """dynamics: backpropagate the returns through the model (continuous actions); reinforce: score-function
    gradient, no gradient through the model."""
    max_grad_norm: float = option(1.0, gt=0)
    """Global gradient-norm clip of the actor and of the critic."""
    net_arch: tuple[int, ...] = (128, 128, 128)
    """Hidden layers of the actor and of the (separate) critic."""
    activation: str = option("elu", choices=("elu", "tanh", "relu"))
    """Activation of both MLPs."""
    log_std_init: float = -1.0
    """Initial log std of the Gaussian actions (learned with the actor; the entropy term keeps it from collapsing)."""
    positive_reward_only: bool = True
    """Clip each step's reward at 0 from below, as the PPO recipe does (no gradient through the clipped steps)."""

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.actor_gradient not in ACTOR_GRADIENTS:
            raise ValueError(f"DreamerConfig.actor_gradient {self.actor_gradient!r} is not one of {ACTOR_GRADIENTS}")
        if not self.net_arch or min(self.net_arch) < 1:
            raise ValueError(f"DreamerConfig.net_arch {self.net_arch} needs at least one layer of >= 1 units")

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


@dataclass
class DreamerStats:
    """One update."""

    timesteps: int
    """Imagined steps so far."""
    imagined_return: float
    """Mean lambda-return of the update's first imagined step (reward plus the critic's bootstrap)."""
    mean_step_reward: float
    actor_grad_norm: float
    """Norm of the actor's gradient before clipping: spikes or a collapse mark where the model's gradient breaks."""
    critic_loss: float
    return_scale: float
    """S, the EMA of the returns' 5-95 percentile range (the actor divides by max(1, S))."""
    entropy: float
    """Entropy of the Gaussian policy (nats, summed over the action dims)."""
    episodes_ended: int
    fraction_terminated: float
    """Share of env-steps that ended in a termination (a predicted fall, tilt, torque halt or divergence)."""
    action_std: float


def lambda_returns(
    rewards: torch.Tensor,
    next_values: torch.Tensor,
    terminated: torch.Tensor,
    done: torch.Tensor,
    gamma: float,
    lam: float,
) -> torch.Tensor:
    """(T, N) lambda-returns of a rollout with auto-reset: `next_values[t]` is the value of the state step t reached
    (before any reset); a terminated step bootstraps nothing, a truncated one its own next value, and no return
    continues across an episode's end. The last step bootstraps its next value alone."""
    horizon = rewards.shape[0]
    returns = [torch.zeros_like(rewards[0])] * horizon
    following = next_values[-1]
    for t in reversed(range(horizon)):
        if t == horizon - 1:
            blend = next_values[t]
        else:
            blend = torch.where(done[t], next_values[t], (1 - lam) * next_values[t] + lam * following)
        returns[t] = rewards[t] + gamma * (~terminated[t]).float() * blend
        following = returns[t]
    return torch.stack(returns)


class Dreamer:
    """The learner: `update()` imagines `horizon` steps and trains the actor and the critic of `policy` in place."""

    def __init__(self, imagination: DifferentiableImagination, policy, config: DreamerConfig, seed: int = 0):
        """policy: an SB3 `ActorCriticPolicy` of `config.ppo_config()`'s layout (`make_ppo(...).policy`)."""
        self.imagination, self.policy, self.config = imagination, policy, config
        self.generator = torch.Generator(device=imagination.device).manual_seed(seed)
        self.actor_parameters = [
            *policy.mlp_extractor.policy_net.parameters(),
            *policy.action_net.parameters(),
            policy.log_std,
        ]
        self.critic = torch.nn.ModuleList([policy.mlp_extractor.value_net, policy.value_net])
        self.actor_optimizer = torch.optim.Adam(self.actor_parameters, lr=config.actor_lr, eps=1e-5)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=config.critic_lr, eps=1e-5)
        self.slow_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.return_scale = 0.0
        self.timesteps = 0

    def _value(self, obs: torch.Tensor, critic: torch.nn.ModuleList) -> torch.Tensor:
        return critic[1](critic[0](self.policy.features_extractor(obs))).squeeze(-1)

    def _mean(self, obs: torch.Tensor) -> torch.Tensor:
        return self.policy.action_net(self.policy.mlp_extractor.forward_actor(self.policy.features_extractor(obs)))

    def entropy(self) -> torch.Tensor:
        """Entropy of the Gaussian policy (its std is state-independent), summed over the action dims."""
        log_std = self.policy.log_std
        return log_std.sum() + 0.5 * log_std.numel() * (1.0 + math.log(2 * math.pi))

    def _rollout(self) -> dict:
        """`horizon` imagined steps from where the envs stand; with dynamics gradients the graph reaches the actor."""
        c, imagination = self.config, self.imagination
        keep_graph = c.actor_gradient == "dynamics"
        rollout: dict = {k: [] for k in ("obs", "raw", "reward", "next_value", "terminated", "done")}
        ended = terminated_count = 0
        with torch.set_grad_enabled(keep_graph):
            for _ in range(c.horizon):
                obs = imagination.observe()
                noise = torch.randn(
                    (obs.shape[0], imagination.spec.action_dim), generator=self.generator, device=obs.device
                )
                raw = self._mean(obs) + self.policy.log_std.exp() * noise
                reward, terminated, truncated = imagination.step(raw.clamp(-1.0, 1.0))
                if c.positive_reward_only:
                    reward = reward.clamp(min=0.0)
                done = terminated | truncated
                rollout["obs"].append(obs.detach())
                rollout["raw"].append(raw.detach())
                rollout["reward"].append(reward)
                rollout["next_value"].append(self._value(imagination.observe(), self.slow_critic))
                rollout["terminated"].append(terminated)
                rollout["done"].append(done)
                finished = np.flatnonzero(done.cpu().numpy())
                ended += len(finished)
                terminated_count += int(terminated.sum())
                imagination.reset(finished)
        stacked = {k: torch.stack(v) for k, v in rollout.items()}
        return {**stacked, "ended": ended, "terminated_count": terminated_count}

    def _normalise(self, returns: torch.Tensor) -> float:
        """Update S, the EMA of the returns' 5-95 percentile range; the divisor max(1, S)."""
        flat = returns.detach().flatten().float()
        spread = float(torch.quantile(flat, 0.95) - torch.quantile(flat, 0.05)) if flat.numel() > 1 else 0.0
        decay = self.config.return_decay if self.timesteps else 0.0  # the first update sets S
        self.return_scale = decay * self.return_scale + (1 - decay) * spread
        return max(1.0, self.return_scale)

    def _actor_loss(self, rollout: dict, returns: torch.Tensor, scale: float) -> torch.Tensor:
        c = self.config
        if c.actor_gradient == "dynamics":
            objective = returns / scale
        else:
            obs = rollout["obs"].flatten(0, 1)
            with torch.no_grad():
                baseline = self._value(obs, self.critic).view_as(returns)
            advantage = (returns.detach() - baseline) / scale
            log_prob = torch.distributions.Normal(self._mean(obs), self.policy.log_std.exp()).log_prob(
                rollout["raw"].flatten(0, 1)
            )
            objective = log_prob.sum(-1).view_as(returns) * advantage
        return -objective.mean() - c.entropy_coef * self.entropy()

    def update(self) -> DreamerStats:
        """One actor step on the lambda-returns of a `horizon`-step imagined rollout, then the critic's."""
        c, n = self.config, self.imagination.core.num_envs
        self.imagination.detach()
        rollout = self._rollout()
        returns = lambda_returns(
            rollout["reward"], rollout["next_value"], rollout["terminated"], rollout["done"], c.gamma, c.return_lambda
        )
        scale = self._normalise(returns)
        loss = self._actor_loss(rollout, returns, scale)
        self.actor_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.actor_parameters, c.max_grad_norm)
        self.actor_optimizer.step()
        critic_loss = self._train_critic(rollout["obs"], returns.detach())
        self.timesteps += n * c.horizon
        return DreamerStats(
            self.timesteps,
            float(returns[0].detach().mean()),
            float(rollout["reward"].detach().mean()),
            float(grad_norm),
            critic_loss,
            self.return_scale,
            float(self.entropy().detach()),
            rollout["ended"],
            rollout["terminated_count"] / (n * c.horizon),
            float(self.policy.log_std.detach().exp().mean()),
        )

    def _train_critic(self, obs: torch.Tensor, targets: torch.Tensor) -> float:
        """Regress V on the lambda-returns (T, N) in minibatches; the slow critic follows by EMA."""
        c = self.config
        flat_obs, flat_targets = obs.reshape(-1, obs.shape[-1]), targets.reshape(-1)
        size = max(1, len(flat_targets) // c.critic_minibatches)
        total, count = 0.0, 0
        for _ in range(c.critic_iterations):
            order = torch.randperm(len(flat_targets), generator=self.generator, device=flat_obs.device)
            for k in range(min(c.critic_minibatches, len(flat_targets))):
                rows = order[k * size : (k + 1) * size]
                loss = (self._value(flat_obs[rows], self.critic) - flat_targets[rows]).square().mean()
                self.critic_optimizer.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(self.critic.parameters(), c.max_grad_norm)
                self.critic_optimizer.step()
                total, count = total + loss.item(), count + 1
        with torch.no_grad():
            for slow, fast in zip(self.slow_critic.parameters(), self.critic.parameters(), strict=True):
                slow.mul_(c.target_critic_decay).add_((1 - c.target_critic_decay) * fast)
        return total / count

    def state_dict(self) -> dict:
        """Everything a resumed run needs besides the policy's own weights (tensors and numbers only)."""
        return {
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "slow_critic": self.slow_critic.state_dict(),
            "return_scale": torch.tensor(self.return_scale, dtype=torch.float64),
            "timesteps": self.timesteps,
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict) -> None:
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.slow_critic.load_state_dict(state["slow_critic"])
        self.return_scale = float(state["return_scale"])
        self.timesteps = int(state["timesteps"])
        self.generator.set_state(state["generator"])
