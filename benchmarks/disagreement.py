"""Does a world model's ensemble disagreement see where it is wrong? The heads against a second, separately trained
model.

The RWM-U penalty reads the disagreement of the model's ensemble heads, which share one GRU trunk. This measures how
well that signal, and the disagreement with a second model (its own trunk), follow the model's real error:

1. On recorded episodes (`--data`, e.g. held-out physics episodes of a policy that exploits the model): windows of
   `--history` true rows, then `--horizon`-step mean forecasts. Per source: the model's error against the data, its
   heads' disagreement, and the second model's (half the mean |difference| of the two forecasts, the std of two
   points); their correlations with the error over windows and steps. All in normalised state units.
2. Inside the model (`--policies`: SB3 zips, `random`, `zero` or `gait`): imagined episodes on the scoring
   commands, from the model's reset data. Per policy: the heads' disagreement along the imagined trajectory and the
   second model's one-step disagreement (it reads the imagined history and predicts the next imagined state), every
   8 steps.

A signal that rises on the data but not inside the model means the policy's troubles lie in states that the model
never predicts it reaches: a penalty cannot find them; physics data of them can.

    python benchmarks/disagreement.py --second runs/wm_bench13/RWM+physics.safetensors \
        --data data/heldout/teacher.h5 data/heldout/imag14_27525120.h5 --policies POLICY.zip random --out DIR
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from rwm_gym.atomic import write_json, write_text
from rwm_gym.data.dataset import Dataset
from rwm_gym.model.checkpoint import load_checkpoint


def windows(path: str, rows: int, stride: int, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, rows, S) states and the (N, rows - 1, A) actions between them, `count` windows drawn from every
    `stride`-th start of every episode."""
    data = Dataset.load(path)
    states, actions = [], []
    for e in range(data.num_episodes):
        episode = data.episode(e)
        for t in range(0, len(episode["state"]) - rows + 1, stride):
            states.append(episode["state"][t : t + rows])
            actions.append(episode["action"][t : t + rows - 1])
    if not states:
        raise SystemExit(f"{path}: no episode holds {rows} rows")
    pick = np.random.default_rng(seed).choice(len(states), min(count, len(states)), replace=False)
    return np.stack([states[i] for i in pick]), np.stack([actions[i] for i in pick])


def correlation(a: np.ndarray, b: np.ndarray) -> float | None:
    """Pearson's r over every window and step; None where either side does not vary (a model against itself)."""
    a, b = a.ravel(), b.ravel()
    return float(np.corrcoef(a, b)[0, 1]) if a.std() > 0 and b.std() > 0 else None


@torch.no_grad()
def on_data(model, meta, second, second_meta, path: str, history: int, horizon: int, count: int, seed: int) -> dict:
    states, actions = windows(path, history + horizon, 8, count, seed)
    a = torch.as_tensor(actions, dtype=torch.float32)
    x = torch.as_tensor(meta.normalizer.normalize_state(states), dtype=torch.float32)
    x2 = torch.as_tensor(second_meta.normalizer.normalize_state(states), dtype=torch.float32)
    mine, _ = model.forecast(x[:, :history], a, horizon, sample=False)
    theirs, _ = second.forecast(x2[:, :history], a, horizon, sample=False)
    error = (mine.state_mean - x[:, history:]).abs().mean(-1).numpy()  # the forecasts are of rows H..H+N-1
    heads = mine.uncertainty.numpy()
    other = ((mine.state_mean - theirs.state_mean).abs() / 2).mean(-1).numpy()
    return {
        "data": path,
        "windows": len(states),
        "error": float(error.mean()),
        "heads": float(heads.mean()),
        "second_model": float(other.mean()),
        "corr_error_heads": correlation(error, heads),
        "corr_error_second_model": correlation(error, other),
    }


@torch.no_grad()
def in_imagination(
    checkpoint: str, reset_data: str | None, second, second_meta, policy: str, history: int, steps: int, seeds: int
) -> dict:
    from rwm_gym.imagination.core import ImaginationOptions, ImaginedCore
    from rwm_gym.rl.evaluate_policy import scoring_commands
    from rwm_gym.rl.score import resolve_policy

    commands = scoring_commands("anymal_d")
    pairs = [(c, s) for c in commands for s in range(seeds)]
    n = len(pairs)
    core = ImaginedCore(
        checkpoint,
        n,
        reset_data=reset_data,
        options=ImaginationOptions(resample_commands=False, report_uncertainty=True),
    )
    act = resolve_policy(policy, n)
    obs = core.reset(np.arange(n), list(range(n)), np.asarray([c for c, _ in pairs], dtype=np.float32))
    states, actions, heads, alive, running = [core.state.copy()], [], [], np.ones(n, bool), []
    for _ in range(steps):
        action = np.clip(act(obs), -1.0, 1.0)
        obs, _, terminated, _, info = core.step(action)
        alive &= ~terminated
        states.append(core.state.copy())
        actions.append(action)
        heads.append(info["uncertainty"])
        running.append(alive.copy())
    x = torch.as_tensor(second_meta.normalizer.normalize_state(np.stack(states, 1)), dtype=torch.float32)
    a = torch.as_tensor(np.stack(actions, 1), dtype=torch.float32)
    u, live = np.stack(heads, 1), np.stack(running, 1)
    other, head = [], []
    for t in range(history, steps - 1, 8):
        p, _ = second.forecast(x[:, t - history + 1 : t + 1], a[:, t - history + 1 : t + 1], 1, sample=False)
        ok = live[:, t]
        other.append(((p.state_mean[:, 0] - x[:, t + 1]).abs() / 2).mean(-1).numpy()[ok])
        head.append(u[ok, t])
    other, head = np.concatenate(other), np.concatenate(head)
    return {
        "policy": policy,
        "episodes": n,
        "running_at_end": int(live[:, -1].sum()),
        "heads": float(head.mean()),
        "second_model_one_step": float(other.mean()),
        "second_model_p90": float(np.quantile(other, 0.9)),
    }


def markdown(report: dict) -> str:
    lines = [
        "| recorded data | windows | error | heads | second model | corr(error, heads) | corr(error, second) |",
        "|---|---|---|---|---|---|---|",
    ]

    def r2(value: float | None) -> str:
        return "-" if value is None else f"{value:.2f}"

    lines += [
        f"| {r['data']} | {r['windows']} | {r['error']:.3f} | {r['heads']:.4f} | {r['second_model']:.3f} | "
        f"{r2(r['corr_error_heads'])} | {r2(r['corr_error_second_model'])} |"
        for r in report["data"]
    ]
    lines += [
        "",
        "| inside the model: policy | episodes running at the end | heads | second model, one step (p90) |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {r['policy']} | {r['running_at_end']} / {r['episodes']} | {r['heads']:.4f} | "
        f"{r['second_model_one_step']:.3f} ({r['second_model_p90']:.3f}) |"
        for r in report["imagination"]
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--checkpoint",
        default="assets/checkpoints/anymal_d_rwm.safetensors",
        help="the world model whose disagreement is judged",
    )
    parser.add_argument("--reset-data", default=None, help="histories of its imagined episodes (default: its own)")
    parser.add_argument("--second", required=True, help="a separately trained world model of the same task")
    parser.add_argument("--data", nargs="*", default=[], help="recorded episodes (HDF5), each a source")
    parser.add_argument(
        "--policies",
        nargs="*",
        default=[],
        help="SB3 zips, 'random' (the datasets' correlated random actions), 'zero' or 'gait', run inside the model",
    )
    parser.add_argument("--history", type=int, default=32)
    parser.add_argument("--horizon", type=int, default=8)
    parser.add_argument("--windows", type=int, default=256)
    parser.add_argument("--steps", type=int, default=120, help="imagined steps per episode")
    parser.add_argument("--seeds", type=int, default=3, help="imagined episodes per scoring command")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.steps <= args.history + 1:
        parser.error(f"--steps {args.steps} leaves no step after a history of {args.history}")
    torch.set_num_threads(1)
    model, meta = load_checkpoint(args.checkpoint)
    model.set_disagreement(True)
    second, second_meta = load_checkpoint(args.second)
    report = {
        "checkpoint": args.checkpoint,
        "second": args.second,
        "history": args.history,
        "horizon": args.horizon,
        "data": [
            on_data(model, meta, second, second_meta, path, args.history, args.horizon, args.windows, args.seed)
            for path in args.data
        ],
        "imagination": [
            in_imagination(
                args.checkpoint, args.reset_data, second, second_meta, policy, args.history, args.steps, args.seeds
            )
            for policy in args.policies
        ],
    }
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "disagreement.json", report)
    table = markdown(report)
    write_text(args.out / "disagreement.md", table)
    print(table + f"wrote {args.out}")


if __name__ == "__main__":
    main()
