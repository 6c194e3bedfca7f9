"""The examples run end to end on tiny budgets (their real budgets are for users, not CI)."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

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
