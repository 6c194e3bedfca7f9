"""Watch the dream beside physics: the world model replays a physics rollout open-loop, frame by frame.

    python examples/dream_vs_physics.py [--checkpoint PATH] [--steps 150] [--out dream_vs_physics.png]

The scripted trot walks in `AnymalD-MuJoCo-v0` at 0.5 m/s; the world model warms up on the first 32 real steps and
then predicts the rest open-loop from the same actions. The top row shows physics, the bottom row the dream (the
predicted state drawn by `DreamRenderer`), every `--every` steps; the title gives the relative L1 state error.
Needs offscreen OpenGL (EGL or OSMesa).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch

from rwm_gym.imagination.core import default_checkpoint
from rwm_gym.imagination.dream import DreamRenderer
from rwm_gym.model.checkpoint import load_checkpoint
from rwm_gym.physics.locomotion import LocomotionEnv
from rwm_gym.policies.gait import GaitPolicy


def physics_rollout(steps: int, seed: int, command: tuple[float, float, float]):
    env = LocomotionEnv(render_mode="rgb_array", width=320, height=240)
    env.reset(seed=seed, options={"command": command})
    core = env.core
    policy = GaitPolicy(env.task_spec, 1)
    policy.reset(np.array([0]), [np.random.default_rng(seed)])
    obs, states, actions, frames = core.observe(), [env.record()["state"]], [], [env.render()]
    for _ in range(steps):
        action = policy.act(obs)
        obs, *_ = core.step(action)
        states.append(env.record()["state"])
        actions.append(action[0])
        frames.append(env.render())
    return np.stack(states), np.stack(actions).astype(np.float32), frames


@torch.no_grad()
def dream(checkpoint: Path, states: np.ndarray, actions: np.ndarray, history: int) -> np.ndarray:
    """Warm up on the first `history` real rows, then predict the remaining rows open-loop (mean predictions)."""
    model, meta = load_checkpoint(checkpoint)
    norm = meta.normalizer
    x = torch.as_tensor(norm.normalize_state(states[None]), dtype=torch.float32)
    u = torch.as_tensor(actions[None])
    horizon = len(states) - history
    prediction, _ = model.forecast(x[:, :history], u, horizon, sample=False)
    predicted = norm.denormalize_state(prediction.state_mean[0].numpy().astype(np.float64))
    return np.concatenate([states[:history], predicted]), prediction.foot_height[0].numpy() * norm.foot_height_std


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, default=None)
    parser.add_argument("--steps", type=int, default=150)
    parser.add_argument("--every", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("dream_vs_physics.png"))
    args = parser.parse_args()
    checkpoint = args.checkpoint or default_checkpoint()
    history = 32

    states, actions, frames = physics_rollout(args.steps, args.seed, (0.5, 0.0, 0.0))
    dreamed, feet = dream(checkpoint, states, actions, history)
    renderer = DreamRenderer(load_checkpoint(checkpoint)[1].spec, height=240, width=320)
    shown = list(range(history, args.steps + 1, args.every))
    dream_frames = {}
    for t in range(history, args.steps + 1):
        foot = feet[t - history - 1] if t > history else np.zeros(4)
        renderer.advance(dreamed[t], foot)
        if t in shown:
            dream_frames[t] = renderer.render()
    std = load_checkpoint(checkpoint)[1].normalizer.state_std
    err = np.abs((dreamed[history:] - states[history:]) / std).sum() / np.abs(states[history:] / std).sum()

    fig, axes = plt.subplots(2, len(shown), figsize=(2.2 * len(shown), 3.6))
    for col, t in enumerate(shown):
        for row, image in enumerate((frames[t], dream_frames[t])):
            axes[row, col].imshow(image)
            axes[row, col].axis("off")
        axes[0, col].set_title(f"t = {(t - history) * 0.02:.1f} s", fontsize=8)
    axes[0, 0].text(-0.1, 0.5, "physics", transform=axes[0, 0].transAxes, rotation=90, va="center", ha="right")
    axes[1, 0].text(-0.1, 0.5, "dream", transform=axes[1, 0].transAxes, rotation=90, va="center", ha="right")
    fig.suptitle(f"open-loop world-model prediction of a physics trot (relative L1 state error {err:.2f})", fontsize=9)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"relative L1 error over {args.steps - history} open-loop steps: {err:.3f}; wrote {args.out}")


if __name__ == "__main__":
    main()
