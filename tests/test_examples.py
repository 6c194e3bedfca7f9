"""The examples run end to end on tiny budgets (their real budgets are for users, not CI)."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import pytest
import torch

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def load_example(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_cleanrl_ppo_trains_on_the_imagined_vector_env(tmp_path):
    example = load_example("cleanrl_ppo")
    args = example.parse_args(["--num-envs", "4", "--num-steps", "8", "--total-steps", "96", "--episode-steps", "10",
                               "--out", str(tmp_path / "actor.pt")])
    result = example.main(args)
    assert result["steps"] == 96 and len(result["mean_step_reward"]) == 3
    assert all(math.isfinite(r) for r in result["mean_step_reward"])
    weights = torch.load(tmp_path / "actor.pt", weights_only=True)
    last = max(k for k in weights if k.endswith(".weight"))
    assert weights[last].shape == (12, 128)  # ANYmal D: 12 joint-position actions


def test_quickstart_runs_clone_warmup_ppo_and_both_evaluations(tmp_path):
    import json
    import os
    import subprocess

    out = tmp_path / "policy.zip"
    tiny = ["--timesteps", "64", "--critic-warmup-steps", "64", "--num-envs", "8", "--n-steps", "8",
            "--net-arch", "32", "--bc-steps", "20", "--eval-seeds", "1", "--eval-steps", "20", "--out", str(out)]
    run = subprocess.run([sys.executable, str(EXAMPLES / "quickstart.py"), *tiny], capture_output=True, text=True,
                         env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "physics evaluation of the cloned actor" in run.stdout and "critic warm-up: 64" in run.stdout
    report = json.loads(out.with_suffix(".json").read_text())
    # the scoring command set (18 commands) x the example's 1 evaluation seed
    assert report["behaviour_cloning"]["evaluation"]["episodes"] == 18 and report["evaluation"]["episodes"] == 18
    assert report["critic_warmup"]["timesteps"] == 64 and report["train"]["timesteps"] == 64
    assert out.is_file() and out.with_name("policy_bc.zip").is_file()
    assert report["kept"] in ("ppo", "behaviour_cloning")  # the verdict is in the JSON
    # the physics samples behind the policy: a count, or (a shipped model older than the count) the reason
    samples, source = report["physics_samples"], report["physics_samples_source"]
    assert (isinstance(samples, int) and samples > 0) or (samples is None and source.startswith("unknown: "))


@pytest.mark.slow  # five commands, each a fresh process (about a minute on idle cores)
def test_gpu_pipeline_runs_every_stage_on_the_cpu(tmp_path):
    """The GPU pipeline's logic on tiny budgets with --device cpu (no GPU on CI; the script is written for one)."""
    example = load_example("gpu_pipeline")
    timings = example.main(["--device", "cpu", "--out", str(tmp_path), "--episodes", "4", "--episode-steps", "80",
                            "--num-envs", "2", "--workers", "2", "--iterations", "4", "--batch-size", "8",
                            "--ppo-timesteps", "256", "--ppo-envs", "8", "--no-ppo-eval"])
    assert list(timings["stages"]) == ["collect_gait", "collect_random", "train", "evaluate", "ppo"]
    assert (tmp_path / "rwm.safetensors").is_file() and (tmp_path / "policy.zip").is_file()
    assert (tmp_path / "timings.json").is_file()
