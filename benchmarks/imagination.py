"""Imagined env-steps/s of RWM-AnymalD-v0 against the model's FLOP ceiling on this machine, beside batched physics
env-steps/s and PPO's own update cost, all measured in one run.

    python benchmarks/imagination.py [--envs 4096] [--seconds 10] [--threads 1] [--device cpu] [--ppo-rollouts 1]

- FLOP per env-step: counted from the checkpoint's layer sizes (`flop_per_env_step`): 2 x in x out for every dense
  weight one step multiplies by (both GRUs: input and hidden weights of every layer; the env's own ensemble head, or
  all k heads when the uncertainty penalty needs their disagreement; the privileged head). Elementwise work (gates,
  activations) is left out: a lower bound on the work, so the ceiling is an upper bound on the speed.
- fp32 matmul GFLOP/s: the best of a square 1024 matmul and the GRU's own (envs x 256) @ (256 x 768) shape, timed in
  this run with the same threads; ceiling env-steps/s = GFLOP/s / FLOP per env-step.
- Imagined and physics rates step random actions in [-0.3, 0.3] and restart finished envs, as a learner would;
  imagined restarts take each window's cached warm-up state (`ImaginationOptions.warm_up_cache_mb`), and the rate
  with a full warm-up on every restart is printed beside it, as is the rate with `nn.GRU`'s own step in place of
  the fused cell (`RWM.fused_step` off), and with the fused cell's products in bfloat16
  (`ImaginationOptions.matmul_precision`; the FLOP ceiling stays the fp32 one). Physics runs on `mujoco.batch`
  with `--threads` threads.
- PPO: SB3's `collect_rollouts` and `train` timed separately for `--ppo-rollouts` rollouts of `rwm_gym.rl.ppo`'s
  defaults (n_steps 24, 5 epochs x 4 minibatches) at the same envs, in imagination.
Prints a table and writes JSON (`--out`).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch

from rwm_gym.atomic import write_json
from rwm_gym.imagination.env import make_imagined_core
from rwm_gym.model.heads import EnsembleLinear
from rwm_gym.physics.locomotion import make_core


def flop_per_env_step(model: torch.nn.Module, *, all_heads: bool = False) -> int:
    """2 x (weights one env-step multiplies by) of an RWM: every GRU / linear weight once, an ensemble layer's one
    member (all k with `all_heads`). Dense layers only; valid for models that use each weight once per step."""
    if model.config.kind != "rwm":
        raise ValueError(f"the FLOP count assumes an RWM (each weight used once per step), not {model.config.kind}")
    total = 0
    for module in model.modules():
        if isinstance(module, EnsembleLinear):
            k, fan_in, fan_out = module.weight.shape
            total += (k if all_heads else 1) * fan_in * fan_out
        elif isinstance(module, torch.nn.Linear):
            total += module.weight.numel()
        elif isinstance(module, torch.nn.GRU):
            total += sum(p.numel() for name, p in module.named_parameters() if name.startswith("weight_"))
    return 2 * total


def matmul_gflops(rows: int, seconds: float, device: str = "cpu") -> dict[str, float]:
    """fp32 GFLOP/s of torch matmul on `device` (the CPU at the current thread count): a square 1024 product and the
    GRU's shape. On a GPU each timed batch of products ends with a synchronisation, so queued work is counted."""
    out = {}
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    for name, (m, k, n) in {"square_1024": (1024, 1024, 1024), f"gru_{rows}x256x768": (rows, 256, 768)}.items():
        a, b = torch.randn(m, k, device=device), torch.randn(k, n, device=device)
        torch.mm(a, b)
        sync()
        calls, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds or calls < 3:
            for _ in range(10):
                torch.mm(a, b)
            sync()
            calls += 10
        out[name] = 2 * m * k * n * calls / (time.perf_counter() - start) / 1e9
    return out


def rate(core, seconds: float) -> float:
    """Env-steps per second of a batched core with auto-restart."""
    n = core.num_envs
    core.reset(np.arange(n), list(range(n)))
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, (8, n, core.spec.action_dim))
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds or steps < 3:
        _, _, terminated, truncated, _ = core.step(actions[steps % 8])
        done = np.flatnonzero(terminated | truncated)
        if len(done):
            core.reset(done)
        steps += 1
    return steps * n / (time.perf_counter() - start)


def ppo_cost(checkpoint, envs: int, rollouts: int, device: str) -> dict[str, float]:
    """Seconds per rollout of SB3 PPO (rwm_gym.rl.ppo defaults) in imagination: collecting it and training on it."""
    from rwm_gym.rl.ppo import PPOConfig, make_ppo
    from rwm_gym.vector.sb3_vec_env import ImaginedSB3VecEnv

    model = make_ppo(ImaginedSB3VecEnv(checkpoint, envs, device=device), PPOConfig(num_envs=envs), seed=0)
    _, callback = model._setup_learn(total_timesteps=envs * model.n_steps * rollouts)
    callback.on_training_start(locals(), globals())
    collect, train = [], []
    for _ in range(rollouts):
        start = time.perf_counter()
        model.collect_rollouts(model.env, callback, model.rollout_buffer, model.n_steps)
        collect.append(time.perf_counter() - start)
        start = time.perf_counter()
        model.train()
        train.append(time.perf_counter() - start)
    samples = envs * model.n_steps
    return {
        "collect_s_per_rollout": float(np.mean(collect)),
        "train_s_per_rollout": float(np.mean(train)),
        "samples_per_rollout": samples,
        "batch_size": model.batch_size,
        "n_epochs": model.n_epochs,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, nargs="+", default=[4096])
    parser.add_argument("--seconds", type=float, default=10.0, help="seconds per timed rate")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--checkpoint", default=None, help="world model (default: the shipped one)")
    parser.add_argument(
        "--uncertainty-penalty",
        type=float,
        default=0.0,
        help="RWM-U penalty of the imagined env (> 0 runs every ensemble head)",
    )
    parser.add_argument(
        "--ppo-rollouts", type=int, default=1, help="PPO rollouts timed at the largest --envs (0: skip)"
    )
    parser.add_argument("--out", type=Path, default=Path("results/imagination_speed.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    probe = make_imagined_core(args.checkpoint, 1, device=args.device)
    flop = flop_per_env_step(probe.model, all_heads=args.uncertainty_penalty > 0)
    gflops = matmul_gflops(max(args.envs), min(args.seconds, 3.0), args.device)
    ceiling = max(gflops.values()) * 1e9 / flop
    rows = []
    for n in args.envs:
        imagined = rate(
            make_imagined_core(args.checkpoint, n, device=args.device, uncertainty_penalty=args.uncertainty_penalty),
            args.seconds,
        )
        uncached = rate(
            make_imagined_core(
                args.checkpoint,
                n,
                device=args.device,
                warm_up_cache_mb=0.0,
                uncertainty_penalty=args.uncertainty_penalty,
            ),
            args.seconds,
        )
        unfused_core = make_imagined_core(
            args.checkpoint, n, device=args.device, uncertainty_penalty=args.uncertainty_penalty
        )
        unfused_core.model.fused_step = False
        unfused = rate(unfused_core, args.seconds)
        bf16 = rate(
            make_imagined_core(
                args.checkpoint,
                n,
                device=args.device,
                matmul_precision="bfloat16",
                uncertainty_penalty=args.uncertainty_penalty,
            ),
            args.seconds,
        )
        physics = rate(make_core("anymal_d", n, nthread=args.threads), args.seconds)
        rows.append(
            {
                "envs": n,
                "imagined_steps_per_s": imagined,
                "ceiling_fraction": imagined / ceiling,
                "imagined_steps_per_s_warm_up_every_reset": uncached,
                "imagined_steps_per_s_nn_gru": unfused,
                "imagined_steps_per_s_bf16": bf16,
                "bf16_speedup": bf16 / imagined,
                "physics_steps_per_s": physics,
                "ratio": imagined / physics,
            }
        )
    # measured again after the rates: on a shared machine the best of the two is the closer estimate of the peak
    again = matmul_gflops(max(args.envs), min(args.seconds, 3.0), args.device)
    gflops = {k: max(v, again[k]) for k, v in gflops.items()}
    ceiling = max(gflops.values()) * 1e9 / flop
    for r in rows:
        r["ceiling_fraction"] = r["imagined_steps_per_s"] / ceiling
    ppo = ppo_cost(args.checkpoint, max(args.envs), args.ppo_rollouts, args.device) if args.ppo_rollouts else None
    load = os.getloadavg()

    print(
        f"model: {flop / 1e6:.3f} MFLOP per env-step ({'all heads' if args.uncertainty_penalty > 0 else 'own head'}"
        f", dense layers); matmul fp32 {', '.join(f'{k} {v:.1f}' for k, v in gflops.items())} GFLOP/s "
        f"({args.threads} threads); ceiling {ceiling:,.0f} env-steps/s; load average {load[0]:.2f}"
    )
    print(
        f"| envs | imagined env-steps/s ({args.device}) | of ceiling | without the warm-up cache "
        f"| with nn.GRU's step (not fused) | bf16 products (x fp32) "
        f"| physics env-steps/s ({args.threads} threads) | imagined / physics |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['envs']} | {r['imagined_steps_per_s']:,.0f} | {r['ceiling_fraction']:.0%} "
            f"| {r['imagined_steps_per_s_warm_up_every_reset']:,.0f} | {r['imagined_steps_per_s_nn_gru']:,.0f} "
            f"| {r['imagined_steps_per_s_bf16']:,.0f} ({r['bf16_speedup']:.2f}x) "
            f"| {r['physics_steps_per_s']:,.0f} | {r['ratio']:.2f} |"
        )
    if ppo:
        per_step = ppo["samples_per_rollout"]
        print(
            f"PPO ({per_step} samples per rollout, batch {ppo['batch_size']}, {ppo['n_epochs']} epochs): collect "
            f"{ppo['collect_s_per_rollout']:.2f} s ({per_step / ppo['collect_s_per_rollout']:,.0f} steps/s), train "
            f"{ppo['train_s_per_rollout']:.2f} s ({per_step / ppo['train_s_per_rollout']:,.0f} samples/s)"
        )
    write_json(
        args.out,
        {
            "threads": args.threads,
            "device": args.device,
            "flop_per_env_step": flop,
            "matmul_gflops": gflops,
            "ceiling_steps_per_s": ceiling,
            "rows": rows,
            "ppo": ppo,
            "loadavg": list(load),
        },
    )


if __name__ == "__main__":
    main()
