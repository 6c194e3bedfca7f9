"""`examples/legged_pipeline.py` chains teacher, data, world model, evaluation, PPO in imagination and scores on the
G1 (legs only) on tiny budgets, on the CPU; run again, it skips what is done and resumes what is not."""

from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
from script_loader import EXAMPLES, ROOT, load_script

import rwm_gym  # noqa: F401  (registers the envs)
from rwm_gym.data.dataset import Dataset
from rwm_gym.model.checkpoint import read_meta
from rwm_gym.policy_zip import load_policy
from rwm_gym.spec import load_spec

TINY = [
    *("--env", str(ROOT / "envs" / "g1_legs.toml"), "--device", "cpu", "--workers", "1"),
    *("--teacher-steps", "1000", "--teacher-envs", "4", "--record-every", "2"),
    *("--random-episodes", "3", "--heldout-episodes", "3", "--episode-steps", "100", "--collect-envs", "3"),
    *("--train-iterations", "4", "--batch-size", "8", "--imagined-steps", "192", "--imagined-envs", "8"),
    *("--score-seeds", "1", "--score-steps", "20", "--score-commands", "0"),
]
"""A few seconds a stage on one core: every stage a few hundred steps."""


def test_a_tiny_g1_chain_runs_every_stage_then_resumes_only_what_is_left(tmp_path, capfd):
    pipeline = load_script(EXAMPLES / "legged_pipeline.py", "example_legged_pipeline")
    out = tmp_path / "g1"
    timings = pipeline.main([*TINY, "--out", str(out)])
    record = json.loads((out / "timings.json").read_text())
    assert list(record["stages"]) == list(pipeline.STAGES) == list(timings["stages"])
    assert record["machine"]["device"] == "cpu" and record["machine"]["cpu_model"]
    for name, entry in record["stages"].items():
        assert entry["wall_s"] > 0 and len(entry["loadavg_after"]) == 3
        assert entry["command"].startswith("merge_datasets(" if name == "merge" else "rwm-gym ")
    assert "--record-every 2" in record["stages"]["teacher"]["command"]

    parts = sorted((out / "teacher" / "experience").glob("part_*.h5"))
    teacher, random = Dataset.load(parts[0]), Dataset.load(out / "data" / "random.h5")
    assert len(parts) == 1 and teacher.num_episodes > 0 and random.num_episodes == 3
    assert Dataset.load(out / "data" / "train.h5").num_episodes == teacher.num_episodes + 3
    heldout = Dataset.load(out / "data" / "heldout.h5")
    assert heldout.num_episodes == 3 and heldout.info.seed == 50000
    assert Dataset.load(out / "data" / "reset.h5").info.metadata["reset_data_from"] == str(parts[0])
    meta = read_meta(out / "rwm.safetensors")
    assert meta.model_config.ensemble_size == 5 and meta.stats["iterations"] == 4
    evaluation = json.loads((out / "evaluation" / "evaluation.json").read_text())
    assert evaluation["data"] == str(out / "data" / "heldout.h5") and evaluation["horizons"][:2] == [8, 32]
    assert evaluation["error"]["8"] > 0 and evaluation["floors"]["no change"]["8"] > 0  # RWM against no change
    for name in ("teacher", "imagination"):
        score = json.loads((out / "score" / name / "score.json").read_text())
        assert score["task"] == "G1Legs" and score["episodes"] == 2 and 0.0 <= score["tracking"] <= 1.0

    state = json.loads((out / "imagination" / "state.json").read_text())
    assert state["timesteps"] == 192 and state["ppo"]["positive_reward_only"]  # the quick start's recipe
    assert state["env"]["imagination"]["reset_data"] == str(out / "data" / "reset.h5")
    policy = load_policy(out / "imagination" / "final.zip", spec=load_spec(ROOT / "envs" / "g1_legs.toml"))
    env = gym.make("G1Legs-MuJoCo-v0")
    obs, _ = env.reset(seed=0)
    action = policy.predict(obs, deterministic=True)[0]
    assert action.shape == (12,) and np.isfinite(action).all()
    assert np.isfinite(env.step(action)[0]).all()

    capfd.readouterr()
    pipeline.main([*TINY, "--out", str(out), "--imagined-steps", "384"])  # a larger budget in imagination
    printed = capfd.readouterr().out
    again = json.loads((out / "timings.json").read_text())
    for name in (*pipeline.STAGES[:6], "score_teacher"):  # done: skipped, their first timing kept
        assert f"[{name}] done, skipped" in printed and again["stages"][name] == record["stages"][name]
    assert "resuming" in printed and json.loads((out / "imagination" / "state.json").read_text())["timesteps"] == 384
    assert again["stages"]["score_imagination"] != record["stages"]["score_imagination"]  # its policy changed
    assert sorted((out / "teacher" / "experience").glob("part_*.h5")) == parts

    pipeline.main([*TINY, "--out", str(out), "--imagined-steps", "384"])  # the same command again: nothing to do
    printed = capfd.readouterr().out
    assert all(f"[{name}] done, skipped" in printed for name in pipeline.STAGES) and "rwm-gym" not in printed
    assert json.loads((out / "timings.json").read_text())["stages"] == again["stages"]
