"""PPO in imagination without Stable-Baselines3: a CleanRL-style single file on the Gymnasium vector env.

    python examples/cleanrl_ppo.py --total-steps 500000 --num-envs 256
    python examples/cleanrl_ppo.py --checkpoint assets/checkpoints/anymal_d_rwm_mbpo.safetensors --num-envs 4096 \
        --episode-steps 50 --uncertainty-penalty 10 --uncertainty-floor 0.02 --uncertainty-halt 0.06 \
        --torque-halt 0.95 --positive-reward-only --log-std-init -1 --learning-rate 1e-3 --total-steps 40000000 \
        --run-dir runs/cleanrl --score

The second line is the walking recipe of `rwm-gym ppo --in imagination`, every setting in view (RWM's KL-adaptive
learning rate is `--target-kl`, on by default); `--run-dir` makes it resumable (the same command continues a killed
run) and `--score` scores the actor in physics at the end, beside the zero-action floor. Seed 0 of that command
walks: tracking 0.862 with 0 falls in 54 physics episodes (the floor is 0.231), 66 min on one CPU thread.

Everything is in this file and reads top to bottom: the batched imagined env `RWM-AnymalD-v0` (one world-model forward
pass steps every env, `gym.make_vec(..., vectorization_mode="vector_entry_point")`), a Gaussian actor and a critic,
GAE, the clipped PPO update, and its resume point. It shows the Gymnasium vector API a hand-written loop sees:
same-step auto-reset, `terminated` vs `truncated`, and `infos["final_obs"]` for bootstrapping at time limits. The
options are the fields of `Args` (their docstrings are the `--help`). It prints one line per update and writes the
actor (safetensors: weights, action std and observation scale; `load_actor` turns it into a policy function).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file
from torch import nn

import rwm_gym  # noqa: F401  (registers the environments)
from rwm_gym.atomic import atomic_write
from rwm_gym.options import add_dataclass_options
from rwm_gym.rl.ppo import observation_scale


@dataclass(frozen=True)
class Args:
    """PPO settings (RWM's figures where they fit a small CPU)."""

    env_id: str = "RWM-AnymalD-v0"
    """Imagined env id (any id with a vector entry point works, e.g. AnymalD-MuJoCo-v0 for physics)."""
    checkpoint: str | None = None
    """World-model checkpoint (None: the shipped one)."""
    num_envs: int = 256
    """Envs stepped together."""
    num_steps: int = 24
    """Steps per env per update."""
    total_steps: int = 200_000
    """Env steps in all."""
    episode_steps: int = 250
    """Time limit of an imagined episode (policy steps)."""
    uncertainty_penalty: float = 0.0
    """RWM-U: reward -lambda * max(u - floor, 0) * dt for the ensemble disagreement u (imagined envs only)."""
    uncertainty_floor: float = 0.0
    """Disagreement left free by the penalty."""
    uncertainty_halt: float = 0.0
    """End an imagined episode (terminated) where the disagreement exceeds this; 0: never."""
    fall_tilt: float = 0.0
    """End an imagined episode (terminated) where the predicted base tilts past this many degrees; 0: never."""
    torque_halt: float = 0.0
    """End an imagined episode (terminated) where a predicted joint torque reaches this fraction of its limit."""
    positive_reward_only: bool = False
    """Clip every step's reward at 0 from below (legged_gym's clip): with negative steps PPO learns to end episodes."""
    log_std_init: float = 0.0
    """Initial log std of the Gaussian actor (-1: std 0.37, the walking recipe's)."""
    learning_rate: float = 3e-4
    """Adam's (initial) learning rate."""
    target_kl: float = 0.01
    """rsl_rl's adaptive learning rate: after an update whose mean approximate KL exceeds 2x this, lr / 1.5; below
    half of it, lr x 1.5 (within 1e-5 .. 1e-2); 0: a fixed learning rate."""
    gamma: float = 0.99
    """Discount per policy step."""
    gae_lambda: float = 0.95
    """GAE lambda."""
    update_epochs: int = 5
    """Passes over each rollout."""
    num_minibatches: int = 4
    """Minibatches per pass."""
    clip_coef: float = 0.2
    """PPO ratio clip."""
    ent_coef: float = 0.005
    """Entropy bonus weight."""
    vf_coef: float = 1.0
    """Value-loss weight."""
    max_grad_norm: float = 1.0
    """Global gradient-norm clip."""
    seed: int = 0
    """Seeds the envs and the networks."""
    out: str = "cleanrl_actor.safetensors"
    """Where the actor is written (weights, log std, observation scale; the Args in its metadata)."""
    run_dir: str | None = None
    """Resumable run folder: a resume point (resume.safetensors) every `save_every` updates; the same command
    continues from it (to a larger --total-steps, too). The envs restart from fresh episodes."""
    save_every: int = 10
    """Updates between resume points (with --run-dir)."""
    score: bool = False
    """At the end, score the actor in physics (`rwm-gym score`'s 18 commands x 3 seeds) beside the zero-action floor."""


RESUMABLE_CHANGES = ("total_steps", "out", "run_dir", "save_every", "score")
"""Args a resumed run may set differently from its first start."""


def mlp(inputs: int, outputs: int, out_gain: float) -> nn.Sequential:
    layers, size = [], inputs
    for hidden in (128, 128, 128):
        layers += [nn.Linear(size, hidden), nn.ELU()]
        size = hidden
    head = nn.Linear(size, outputs)
    nn.init.orthogonal_(head.weight, out_gain)
    nn.init.zeros_(head.bias)
    return nn.Sequential(*layers, head)


class Agent(nn.Module):
    """Gaussian actor (state-independent log std) and critic on observations scaled by the task's fixed constants."""

    def __init__(self, obs_mean: list[float], obs_std: list[float], actions: int, log_std_init: float = 0.0):
        super().__init__()
        self.register_buffer("obs_mean", torch.tensor(obs_mean))
        self.register_buffer("obs_std", torch.tensor(obs_std))
        self.actor = mlp(len(obs_mean), actions, 0.01)
        self.critic = mlp(len(obs_mean), 1, 1.0)
        self.log_std = nn.Parameter(torch.full((actions,), log_std_init))

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.critic((obs - self.obs_mean) / self.obs_std).squeeze(-1)

    def act(self, obs: torch.Tensor, action: torch.Tensor | None = None):
        x = (obs - self.obs_mean) / self.obs_std
        dist = torch.distributions.Normal(self.actor(x), self.log_std.exp())
        if action is None:
            action = dist.sample()
        return action, dist.log_prob(action).sum(-1), dist.entropy().sum(-1), self.critic(x).squeeze(-1)

    @torch.no_grad()
    def mean_action(self, obs: torch.Tensor) -> torch.Tensor:
        """The deterministic action, clipped to the action space as the env clips it."""
        return self.actor((obs - self.obs_mean) / self.obs_std).clamp(-1, 1)


def save_actor(agent: Agent, path: str | Path, args: Args) -> Path:
    """The actor alone, all a policy needs (the critic and Adam's moments stay in the resume point)."""
    tensors = {f"actor.{k}": v for k, v in agent.actor.state_dict().items()}
    tensors |= {"log_std": agent.log_std.detach(), "obs_mean": agent.obs_mean, "obs_std": agent.obs_std}
    tensors = {k: v.contiguous() for k, v in tensors.items()}
    return atomic_write(path, lambda tmp: save_file(tensors, tmp, metadata={"args": json.dumps(asdict(args))}))


def load_actor(path: str | Path):
    """A deterministic policy function (the mean action, clipped to [-1, 1]) from a file `save_actor` wrote; it is
    what `rwm_gym.rl.score.score` and `rwm_gym.rl.evaluate_policy` take."""
    tensors = load_file(path)
    agent = Agent(tensors["obs_mean"].tolist(), tensors["obs_std"].tolist(), len(tensors["log_std"]))
    agent.actor.load_state_dict({k.removeprefix("actor."): v for k, v in tensors.items() if k.startswith("actor.")})
    return lambda obs: agent.mean_action(torch.as_tensor(obs, dtype=torch.float32)).numpy()


def save_resume_point(path: Path, agent: Agent, optimizer: torch.optim.Adam, progress: dict) -> None:
    """Agent, Adam's moments and torch's generator in one safetensors file, the counters as its JSON metadata: one
    atomic write, so a killed save leaves the previous point whole."""
    tensors = {f"agent.{k}": v for k, v in agent.state_dict().items()}
    for i, state in optimizer.state_dict()["state"].items():
        tensors |= {f"adam.{i}.{k}": torch.as_tensor(v) for k, v in state.items()}
    tensors["torch_rng"] = torch.get_rng_state()
    tensors = {k: v.detach().contiguous() for k, v in tensors.items()}
    atomic_write(path, lambda tmp: save_file(tensors, tmp, metadata={"progress": json.dumps(progress)}))


def load_resume_point(path: Path, agent: Agent, optimizer: torch.optim.Adam, args: Args) -> dict:
    """Restore what `save_resume_point` wrote; refuses a folder started with other settings."""
    with safe_open(path, "pt") as f:
        progress = json.loads(f.metadata()["progress"])
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    started, now = progress["args"], asdict(args)
    changed = [k for k in now if k not in RESUMABLE_CHANGES and started.get(k) != now[k]]
    if changed:
        raise SystemExit(
            f"cleanrl_ppo: {path.parent} was started with other settings ({', '.join(changed)}); use another --run-dir"
        )
    agent.load_state_dict({k.removeprefix("agent."): v for k, v in tensors.items() if k.startswith("agent.")})
    moments: dict[int, dict] = {}
    for key, value in tensors.items():
        if key.startswith("adam."):
            _, index, name = key.split(".")
            moments.setdefault(int(index), {})[name] = value
    optimizer.load_state_dict({"state": moments, "param_groups": optimizer.state_dict()["param_groups"]})
    torch.set_rng_state(tensors["torch_rng"])
    return progress


def main(args: Args) -> dict:
    torch.manual_seed(args.seed)
    kwargs = {}
    if args.env_id.startswith("RWM-"):
        kwargs = {
            "checkpoint": args.checkpoint,
            "episode_steps": args.episode_steps,
            "uncertainty_penalty": args.uncertainty_penalty,
            "uncertainty_floor": args.uncertainty_floor,
            "uncertainty_halt": args.uncertainty_halt,
            "fall_tilt": args.fall_tilt,
            "torque_halt": args.torque_halt,
        }
    envs = gym.make_vec(args.env_id, num_envs=args.num_envs, vectorization_mode="vector_entry_point", **kwargs)
    n, obs_dim = args.num_envs, envs.single_observation_space.shape[0]
    act_dim = envs.single_action_space.shape[0]
    agent = Agent(*observation_scale(envs.unwrapped.core.spec), act_dim, args.log_std_init)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)

    resume = Path(args.run_dir) / "resume.safetensors" if args.run_dir else None
    progress = {
        "args": asdict(args),
        "update": 0,
        "step": 0,
        "episodes": 0,
        "lr": args.learning_rate,
        "restarts": 0,
        "wall_s": 0.0,
        "mean_step_reward": [],
    }
    if resume is not None and resume.is_file():
        progress = load_resume_point(resume, agent, optimizer, args)
        progress["restarts"] += 1
        progress["args"] = asdict(args)
        print(f"resuming {args.run_dir} at {progress['step']:,} steps (restart {progress['restarts']})", flush=True)

    obs_buf = torch.zeros(args.num_steps, n, obs_dim)
    act_buf = torch.zeros(args.num_steps, n, act_dim)
    logp_buf, rew_buf, done_buf, val_buf = (torch.zeros(args.num_steps, n) for _ in range(4))
    batch = args.num_steps * n
    minibatch = batch // args.num_minibatches

    obs, _ = envs.reset(seed=args.seed + 7919 * progress["restarts"])  # a resumed run starts fresh episodes
    obs = torch.as_tensor(obs)
    started, lr = time.monotonic() - progress["wall_s"], progress["lr"]
    for group in optimizer.param_groups:
        group["lr"] = lr
    episode_return = np.zeros(n)
    for update in range(progress["update"] + 1, args.total_steps // batch + 1):
        finished = []
        for t in range(args.num_steps):
            with torch.no_grad():
                action, logp, _, value = agent.act(obs)
            next_obs, reward, terminated, truncated, infos = envs.step(action.clamp(-1, 1).numpy())
            episode_return += reward
            reward = torch.as_tensor(reward, dtype=torch.float32)
            if args.positive_reward_only:
                reward = reward.clamp(min=0.0)
            if "_final_obs" in infos:  # bootstrap through time limits: the episode did not end, it was cut
                cut = np.flatnonzero(infos["_final_obs"] & truncated)
                if len(cut):
                    final = torch.as_tensor(np.stack([infos["final_obs"][i] for i in cut]))
                    with torch.no_grad():
                        reward[cut] += args.gamma * agent.value(final)
            done = terminated | truncated
            finished += episode_return[done].tolist()
            episode_return[done] = 0.0
            obs_buf[t], act_buf[t], logp_buf[t], val_buf[t] = obs, action, logp, value
            rew_buf[t], done_buf[t] = reward, torch.as_tensor(done, dtype=torch.float32)
            obs = torch.as_tensor(next_obs)

        with torch.no_grad():  # generalised advantage estimation
            advantages = torch.zeros_like(rew_buf)
            last_gae, next_value = torch.zeros(n), agent.value(obs)
            for t in reversed(range(args.num_steps)):
                not_done = 1.0 - done_buf[t]
                delta = rew_buf[t] + args.gamma * next_value * not_done - val_buf[t]
                last_gae = delta + args.gamma * args.gae_lambda * not_done * last_gae
                advantages[t], next_value = last_gae, val_buf[t]
            returns = advantages + val_buf

        b_obs, b_act = obs_buf.reshape(batch, obs_dim), act_buf.reshape(batch, act_dim)
        b_logp, b_adv, b_ret = logp_buf.reshape(-1), advantages.reshape(-1), returns.reshape(-1)
        kls = []
        for _ in range(args.update_epochs):
            for idx in torch.randperm(batch).split(minibatch):
                _, logp, entropy, value = agent.act(b_obs[idx], b_act[idx])
                log_ratio = logp - b_logp[idx]
                ratio = log_ratio.exp()
                adv = (b_adv[idx] - b_adv[idx].mean()) / (b_adv[idx].std() + 1e-8)
                policy_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
                loss = policy_loss + args.vf_coef * ((value - b_ret[idx]) ** 2).mean() - args.ent_coef * entropy.mean()
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()
                kls.append(float(((ratio - 1) - log_ratio).mean().detach()))  # Schulman's low-variance estimate

        kl = float(np.mean(kls))
        if args.target_kl > 0:  # rsl_rl's schedule, once per update
            if kl > 2 * args.target_kl:
                lr = max(1e-5, lr / 1.5)
            elif kl < args.target_kl / 2:
                lr = min(1e-2, lr * 1.5)
            for group in optimizer.param_groups:
                group["lr"] = lr
        mean_step_reward = float(rew_buf.mean())
        progress["mean_step_reward"].append(mean_step_reward)
        progress.update(
            update=update,
            step=progress["step"] + batch,
            episodes=progress["episodes"] + len(finished),
            lr=lr,
            wall_s=time.monotonic() - started,
        )
        ended = (
            f"{len(finished):4d} episodes ended, mean return {np.mean(finished):+.3f}"
            if finished
            else "no episode ended"
        )
        print(
            f"update {update:4d}  steps {progress['step']:9d}  mean step reward {mean_step_reward:+.5f}  {ended}  "
            f"kl {kl:.4f}  lr {lr:.1e}  {progress['step'] / progress['wall_s']:6.0f} steps/s",
            flush=True,
        )
        if resume is not None and update % args.save_every == 0:
            save_resume_point(resume, agent, optimizer, progress)

    envs.close()
    if resume is not None:
        save_resume_point(resume, agent, optimizer, progress)
    print(f"wrote {save_actor(agent, args.out, args)}")
    result = {
        "steps": progress["step"],
        "mean_step_reward": progress["mean_step_reward"],
        "episodes": progress["episodes"],
        "lr": lr,
    }
    if args.score:
        from rwm_gym.rl.score import score, summary_line, zero_policy

        policy, floor = score(load_actor(args.out)), score(zero_policy)
        print(summary_line(f"{args.out} in physics", policy))
        print(summary_line("zero-action floor in physics", floor))
        result |= {"tracking": policy.tracking, "falls": policy.falls, "floor": floor.tracking}
    return result


def parse_args(argv: list[str] | None = None) -> Args:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_dataclass_options(parser, Args, types={"checkpoint": str})
    return Args(**vars(parser.parse_args(argv)))


if __name__ == "__main__":
    main(parse_args())
