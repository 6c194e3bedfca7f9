"""`examples/coverage_rounds.py` chains two coverage rounds of two PPO seeds each on the Go2 on tiny budgets; run
again, it writes nothing."""

from __future__ import annotations

import json

from script_loader import EXAMPLES, load_script

from rwm_gym.cli import main as rwm_gym
from rwm_gym.data.dataset import Dataset
from rwm_gym.imagination.reset_data import make_reset_data
from rwm_gym.model.checkpoint import read_meta
from tests.test_new_robot import TINY_TRAIN


def test_two_tiny_go2_rounds_chain_model_buffer_and_policies_then_resume_to_nothing_new(tmp_path, capsys):
    base, start = tmp_path / "base.h5", tmp_path / "start.safetensors"
    collect = ["collect", "--env", "Go2-MuJoCo-v0", "--policy", "random", "--episodes", "4", "--max-steps", "40"]
    assert rwm_gym([*collect, "--out", str(base)]) == 0
    assert rwm_gym(["train", "--data", str(base), "--out", str(start), *TINY_TRAIN, "--ensemble-size", "5"]) == 0
    reset = make_reset_data(base, tmp_path / "reset.h5", episodes=4)
    out = tmp_path / "cover"
    argv = [
        *("--checkpoint", str(start), "--base", str(base), "--policies", "zero", "--reset-data", str(reset)),
        *("--out", str(out), "--rounds", "2", "--keep-going", "--episodes", "2", "--max-steps", "30"),
        *("--iterations", "4", "--timesteps", "384", "--num-envs", "8", "--threads", "1"),
        *("--score-seeds", "1", "--score-steps", "20", "--score-commands", "0", "--extra-seeds", "5", "--mirror"),
    ]
    example = load_script(EXAMPLES / "coverage_rounds.py", "example_coverage_rounds")
    rows = example.main(argv)

    assert json.loads((out / "rounds.json").read_text()) == rows and [row["round"] for row in rows] == [1, 2]
    for k, row in enumerate(rows, 1):
        score = json.loads((out / f"round_{k}" / "ppo" / "score" / "score.json").read_text())
        assert (row["tracking"], row["falls"], row["episodes"]) == (score["tracking"], score["falls"], 2)
        assert row["floor"] == score["floor"] and row["timesteps"] == 384
        assert set(row["wall_s"]) == set(row["loadavg"]) == {"fine_tune", "ppo", "score", "ppo_s5", "score_s5"}
        assert [run["seed"] for run in row["runs"]] == [k, 5]
        extra = json.loads((out / f"round_{k}" / "ppo_s5" / "score" / "score.json").read_text())
        assert (row["runs"][1]["tracking"], row["runs"][1]["falls"]) == (extra["tracking"], extra["falls"])
        assert json.loads((out / f"round_{k}" / "ppo_s5" / "policy.json").read_text())["seed"] == 5
        assert json.loads((out / f"round_{k}" / "ppo" / "state.json").read_text())["ppo"]["positive_reward_only"]
    first, second = (out / f"round_{k}" for k in (1, 2))
    meta = read_meta(second / "model.safetensors")
    assert meta.provenance["init_checkpoint"] == str(first / "model.safetensors")
    assert meta.train_config.mirror and read_meta(first / "model.safetensors").train_config.mirror  # --mirror
    # each round-1 run's snapshot nearest 50 % and 75 % of its budget (2 rollouts, snapshot every 24: only step 0),
    # then its policy
    runs = [first / "ppo", first / "ppo_s5"]
    assert meta.extras["policies"] == [
        str(run / name) for run in runs for name in ("snapshots/step_0.zip", "policy.zip")
    ]
    parts = sorted((second / "own").glob("part_*.h5"))
    assert len(parts) == 8 and Dataset.load(parts[0]).info.seed == 82_000  # 4 policies x 2 noise levels
    own = sum(Dataset.load(p).num_steps for p in parts)
    assert Dataset.load(second / "buffer.h5").num_steps == Dataset.load(first / "buffer.h5").num_steps + own
    assert rows[1]["physics_rows"] == meta.extras["physics_rows"] and rows[1]["physics_rows"]["own"] == own
    printed = capsys.readouterr().out
    assert "round 2, seed 5: tracking" in printed

    files = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    assert example.main(argv) == rows
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()} == files
    again = capsys.readouterr().out
    assert [line.split(":")[0] for line in again.splitlines()] == [
        f"round {k}, seed {s}" for k in (1, 2) for s in (k, 5)
    ]
