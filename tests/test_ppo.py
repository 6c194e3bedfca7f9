"""PPO in physics and imagination, the physics evaluation, and `rwm-gym ppo`: tiny budgets, real checks."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from stable_baselines3 import PPO

from rwm_gym.cli import main
from rwm_gym.imagination.options import ImaginationOptions
from rwm_gym.rl.evaluate_policy import evaluate_policy, format_table, plot
from rwm_gym.rl.ppo import PPOConfig, learn, make_env, make_ppo, warm_up_critic

TINY = PPOConfig(num_envs=8, n_steps=16, net_arch=(32, 32))


def test_config_refuses_bad_values():
    with pytest.raises(ValueError, match="activation"):
        PPOConfig(activation="gelu")
    with pytest.raises(ValueError, match="num_minibatches"):
        PPOConfig(num_envs=3, n_steps=3, num_minibatches=4)


def test_ppo_trains_in_physics():
    model = make_ppo(make_env("physics", TINY.num_envs, seed=0), TINY, seed=0)
    before = [p.detach().clone() for p in model.policy.parameters()]
    stats = learn(model, timesteps=3 * TINY.num_envs * TINY.n_steps, progress=False)
    assert stats.timesteps == 3 * TINY.num_envs * TINY.n_steps and stats.steps_per_s > 0
    assert [row["timesteps"] for row in stats.log] == [128, 256, 384]
    assert all(np.isfinite(row["mean_step_reward"]) for row in stats.log)
    assert any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters()))
    assert model.policy.log_std.shape == (12,)


def test_cli_ppo_in_physics_writes_zip_and_report(tmp_path, capsys):
    out = tmp_path / "policy.zip"
    rc = main(
        [
            "ppo",
            "--in",
            "physics",
            "--timesteps",
            "256",
            "--num-envs",
            "8",
            "--n-steps",
            "16",
            "--net-arch",
            "32",
            "32",
            "--out",
            str(out),
            "--eval-seeds",
            "1",
            "--eval-steps",
            "20",
            "--threads",
            "1",
        ]
    )
    assert rc == 0 and out.is_file() and out.with_suffix(".png").is_file()
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["where"] == "physics" and report["ppo"]["net_arch"] == [32, 32]
    assert report["physics_samples"] == report["train"]["timesteps"] >= 256
    assert report["physics_samples_source"] == "the policy's own physics steps"
    printed = capsys.readouterr().out
    assert f"physics samples behind the policy: {report['physics_samples']:,}" in printed
    assert not re.search(r"\d\.\d{5,}", printed)  # every figure printed to a sensible precision
    assert report["evaluation"]["episodes"] == 18 and len(report["evaluation"]["commands"]) == 18  # the scoring set
    model = PPO.load(out, device="cpu")
    action, _ = model.predict(np.zeros(48, np.float32), deterministic=True)
    assert action.shape == (12,)


def test_evaluation_of_a_standing_policy(tmp_path):
    stand = lambda obs: np.zeros((len(obs), 12))  # noqa: E731
    commands = [(0.5, 0.0, 0.0), (0.0, 0.0, 0.5)]
    result = evaluate_policy(stand, commands=commands, seeds=[0, 1], steps=40, settle_steps=10)
    assert result.episodes == 4 and result.steps == 40 and result.falls == 0
    forward, turn = result.commands
    assert forward.command == (0.5, 0.0, 0.0)
    assert abs(forward.lin_vel_error - 0.5) < 0.05 and abs(turn.yaw_rate_error - 0.5) < 0.05  # it stands still
    assert abs(forward.distance) < 0.05 and max(abs(v) for v in forward.achieved) < 0.05
    assert result.lin_vel_error == pytest.approx((forward.lin_vel_error + turn.lin_vel_error) / 2)
    again = evaluate_policy(stand, commands=commands, seeds=[0, 1], steps=40, settle_steps=10)
    assert again.commands == result.commands  # fixed commands and seeds: deterministic
    assert "(+0.5, +0.0, +0.0)" in format_table(result)
    assert plot(result, tmp_path / "eval.png").stat().st_size > 0


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory):
    """A small RWM trained briefly on a few random physics episodes."""
    pytest.importorskip("rwm_gym.vector.sb3_vec_env")
    from rwm_gym.data.collect import collect
    from rwm_gym.model.config import TrainConfig
    from rwm_gym.model.factory import model_config_for
    from rwm_gym.model.train import train
    from rwm_gym.spec import load_spec

    folder = tmp_path_factory.mktemp("tiny_rwm")
    data = collect(
        "AnymalD-MuJoCo-v0", "random", 6, folder / "data.h5", seed=0, num_envs=6, max_steps=60, progress=False
    )
    config = model_config_for("rwm", load_spec("anymal_d"), hidden_size=64, num_layers=1, head_hidden=64)
    train_config = TrainConfig(history=8, forecast=4, iterations=100, batch_size=32, val_every=100, val_fraction=0.2)
    return train(data, config, train_config, folder / "tiny.safetensors", progress=False).path


def test_ppo_trains_in_imagination(tiny_checkpoint):
    """SB3 PPO runs on the imagined VecEnv: time-limit bootstraps, episode returns logged, the policy moves.

    (That the imagined return rises is not asserted: on this tiny, briefly trained model it is not robust across seeds
    within a test-sized budget.)"""
    config = PPOConfig(num_envs=32, n_steps=25, net_arch=(64, 64))
    env = make_env("imagination", config.num_envs, checkpoint=tiny_checkpoint, seed=0, env_kwargs={"episode_steps": 25})
    model = make_ppo(env, config, seed=0)
    before = [p.detach().clone() for p in model.policy.parameters()]
    stats = learn(model, timesteps=3 * config.num_envs * config.n_steps, progress=False)
    assert len(stats.log) == 3 and all(row["episodes"] >= config.num_envs for row in stats.log)
    assert all(np.isfinite(row["mean_episode_return"]) for row in stats.log)
    # an episode is 25 steps here, so its return is 25 x the mean step reward up to episodes cut by a fall
    row = stats.log[0]
    assert abs(row["mean_episode_return"]) <= 25 * abs(row["mean_step_reward"]) * 1.5 + 1e-6
    assert any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters()))


def test_critic_warm_up_trains_only_the_critic(tiny_checkpoint):
    config = PPOConfig(num_envs=16, n_steps=16, net_arch=(32, 32))
    model = make_ppo(make_env("imagination", config.num_envs, checkpoint=tiny_checkpoint, seed=0), config, seed=0)
    policy = model.policy
    actor = [*policy.mlp_extractor.policy_net.parameters(), *policy.action_net.parameters(), policy.log_std]
    critic = [*policy.mlp_extractor.value_net.parameters(), *policy.value_net.parameters()]
    actor_before = [p.detach().clone() for p in actor]
    critic_before = [p.detach().clone() for p in critic]
    stats = warm_up_critic(model, 2 * config.num_envs * config.n_steps, progress=False)
    assert stats.timesteps == 2 * config.num_envs * config.n_steps
    assert all(torch.equal(a, b) for a, b in zip(actor_before, actor))
    assert any(not torch.equal(a, b) for a, b in zip(critic_before, critic))
    assert all(p.requires_grad for p in actor)  # the actor trains again afterwards
    learn(model, timesteps=config.num_envs * config.n_steps, progress=False)
    assert any(not torch.equal(a, b) for a, b in zip(actor_before, actor))


def test_imagined_return_rises_on_the_shipped_model():
    """PPO on RWM-AnymalD-v0 improves the imagined reward within a test budget.

    Episodes last one rollout (24 steps) and resets desynchronise them, so the reward of a rollout follows a pattern
    of period 5 rollouts; we compare whole periods. The critic warm-up keeps the actor frozen, so its two periods
    measure the initial policy; after 25 updates the last period must beat both.
    """
    config = PPOConfig(num_envs=64, n_steps=24, net_arch=(64, 64), learning_rate=3e-3, target_kl=0.0, ent_coef=0.0)
    env = make_env("imagination", config.num_envs, checkpoint=None, seed=0, env_kwargs={"episode_steps": 24})
    model = make_ppo(env, config, seed=0)
    rollout = config.num_envs * config.n_steps
    before = [row["mean_step_reward"] for row in warm_up_critic(model, 10 * rollout, progress=False).log]
    after = [row["mean_step_reward"] for row in learn(model, timesteps=25 * rollout, target_kl=0.0, progress=False).log]
    initial = max(np.mean(before[:5]), np.mean(before[5:10]))
    assert np.mean(after[-5:]) > initial + 0.1 * abs(initial), (before, after)


def test_mbpo_loop_fine_tunes_counts_samples_and_resumes_to_the_same_numbers(tiny_checkpoint, tmp_path, monkeypatch):
    import rwm_gym.data.dataset
    from rwm_gym.data.collect import collect
    from rwm_gym.data.dataset import Dataset
    from rwm_gym.model.checkpoint import read_meta
    from rwm_gym.rl.mbpo import MBPOConfig, mbpo

    data = collect(
        "AnymalD-MuJoCo-v0", "random", 4, tmp_path / "data.h5", seed=3, num_envs=4, max_steps=60, progress=False
    )
    start = make_ppo(
        make_env("imagination", 8, checkpoint=tiny_checkpoint, seed=0),
        PPOConfig(num_envs=8, n_steps=16, net_arch=(32, 32)),
        seed=0,
    )
    start.save(tmp_path / "start.zip")
    config = MBPOConfig(
        iterations=2,
        ppo_timesteps=128,
        num_envs=8,
        imagination=ImaginationOptions(episode_steps=20),
        collect_episodes=2,
        collect_steps=48,
        base_episodes=3,
        model_iterations=5,
        model_finetune=True,
        model_lr=3e-4,
        critic_warmup_steps=128,
        eval_seeds=1,
        eval_steps=20,
    )
    run = dict(checkpoint=tiny_checkpoint, init_policy=tmp_path / "start.zip", progress=False)
    merged_into, merge = [], rwm_gym.data.dataset.merge_datasets
    monkeypatch.setattr(
        rwm_gym.data.dataset, "merge_datasets", lambda paths, out: merged_into.append(out) or merge(paths, out)
    )
    report = mbpo(data, tmp_path / "mbpo", config, **run)
    monkeypatch.undo()
    assert [Path(p).name for p in merged_into].count("buffer.h5") == 2  # once per iteration, not again at the next
    log = report["log"]
    assert [row["iteration"] for row in log] == [0, 1, 2]
    assert log[0]["model_error_fresh"] is None and all(row["model_error_fresh"] for row in log[1:])
    rows = [row["physics_samples"] for row in log]
    fresh = [Dataset.load(tmp_path / "mbpo" / f"data_{k}.h5").num_steps for k in (1, 2)]
    behind_model = read_meta(tiny_checkpoint).provenance["physics_rows"]  # the starting model's own data counts too
    assert rows == [behind_model + Dataset.load(data).num_steps, rows[0] + fresh[0], rows[0] + fresh[0] + fresh[1]]
    model_1 = read_meta(tmp_path / "mbpo" / "model_1.safetensors").provenance["physics_rows"]
    assert model_1 == rows[1]  # the fine-tuned model's lineage: its start's, the buffer's base and the fresh rows
    assert Dataset.load(tmp_path / "mbpo" / "buffer.h5").num_episodes == 3 + 2 + 2  # base + both collections
    assert report["best_tracking"] == max(row["tracking"] for row in log)
    assert report["ppo"] == {"init_policy": str(tmp_path / "start.zip")}  # settings from the zip, not defaults
    for k in (1, 2):  # each model is fine-tuned from the one before
        previous = tmp_path / "mbpo" / f"model_{k - 1}.safetensors"
        assert read_meta(tmp_path / "mbpo" / f"model_{k}.safetensors").provenance["init_checkpoint"] == str(previous)
    assert (tmp_path / "mbpo" / "mbpo.png").stat().st_size > 0
    assert json.loads((tmp_path / "mbpo" / "mbpo.json").read_text())["log"] == json.loads(json.dumps(log))

    # stopped after iteration 1 and resumed: the same numbers as the run never stopped
    first = mbpo(data, tmp_path / "resumed", replace(config, iterations=1), **run)
    assert len(first["log"]) == 2
    curve = tmp_path / "model_free.csv"
    curve.write_text("timesteps,wall_s,tracking\n0,0,0.23\n1000,5,0.5\n")
    resumed = mbpo(data, tmp_path / "resumed", config, model_free_curve=curve, **run)["log"]
    numbers = ("tracking", "physics_return", "falls", "physics_samples", "imagined_step_reward", "model_error_fresh")
    assert [[row[n] for n in numbers] for row in resumed] == [[row[n] for n in numbers] for row in log]
    curve.write_text("steps,score\n0,0.2\n")
    with pytest.raises(ValueError, match="needs 'timesteps' and 'tracking' columns"):
        mbpo(data, tmp_path / "resumed", config, model_free_curve=curve, **run)
    with pytest.raises(ValueError, match="other settings \\(model_lr\\)"):
        mbpo(data, tmp_path / "resumed", replace(config, model_lr=1e-3), **run)


def test_mbpo_trains_on_clipped_rewards_and_starts_a_fresh_policy_at_its_log_std(
    tiny_checkpoint, tmp_path, monkeypatch
):
    from rwm_gym.data.collect import collect
    from rwm_gym.rl import ppo
    from rwm_gym.rl.mbpo import MBPOConfig, mbpo

    data = collect(
        "AnymalD-MuJoCo-v0", "random", 2, tmp_path / "data.h5", seed=3, num_envs=2, max_steps=40, progress=False
    )
    seen = []
    real_learn = ppo.learn

    def learn(model, **kwargs):  # what PPO trains on: the env wrapper and the rewards it is given
        rewards = []
        venv = model.get_env()
        step_wait = venv.step_wait

        def record():
            obs, reward, done, infos = step_wait()
            rewards.append(reward.copy())
            return obs, reward, done, infos

        venv.step_wait = record
        stats = real_learn(model, **kwargs)
        seen.append((type(venv), np.concatenate(rewards)))
        return stats

    monkeypatch.setattr(ppo, "learn", learn)
    config = MBPOConfig(
        iterations=1,
        ppo_timesteps=64,
        num_envs=8,
        imagination=ImaginationOptions(episode_steps=20),
        collect_episodes=1,
        collect_steps=48,
        model_iterations=2,
        model_finetune=True,
        eval_seeds=1,
        eval_steps=10,
        positive_reward_only=True,
        log_std_init=-1.0,
    )
    report = mbpo(data, tmp_path / "mbpo", config, checkpoint=tiny_checkpoint, progress=False)
    [(wrapper, rewards)] = seen
    assert wrapper is ppo.PositiveReward and rewards.size and rewards.min() >= 0.0
    assert report["ppo"]["positive_reward_only"] and report["ppo"]["log_std_init"] == -1.0
    start = PPO.load(tmp_path / "mbpo" / "policy_0.zip")
    assert np.allclose(start.policy.log_std.detach().numpy(), -1.0)


def test_mbpo_trains_its_own_starting_model_with_an_ensemble_where_the_halt_needs_one(tmp_path):
    from rwm_gym.data.collect import collect
    from rwm_gym.model.checkpoint import read_meta
    from rwm_gym.rl.mbpo import MBPOConfig, mbpo

    data = collect(
        "AnymalD-MuJoCo-v0", "random", 2, tmp_path / "data.h5", seed=3, num_envs=2, max_steps=60, progress=False
    )
    config = MBPOConfig(
        iterations=0,
        num_envs=8,
        model_iterations=1,
        eval_seeds=1,
        eval_steps=10,
        imagination=ImaginationOptions(episode_steps=20, uncertainty_halt=0.06),
    )
    mbpo(data, tmp_path / "mbpo", config, progress=False)
    assert read_meta(tmp_path / "mbpo" / "model_0.safetensors").model_config.ensemble_size == 5


def test_an_mbpo_run_from_before_a_new_field_resumes_with_its_default(tmp_path):
    from rwm_gym.rl.mbpo import MBPOConfig, _check_resume

    # a run folder of 0.1: the imagination options flat beside the loop's, without the fields added since
    older = {k: v for k, v in MBPOConfig().to_dict().items() if k != "imagination"}
    older.update(
        imagined_episode_steps=250,
        uncertainty_penalty=0.0,
        fall_tilt=0.0,
        torque_halt=0.0,
        random_first_episode_length=False,
        trust_entry_points=False,
    )
    _check_resume({"config": older}, MBPOConfig(iterations=9), tmp_path / "mbpo.json")  # only iterations changed
    with pytest.raises(ValueError, match="other settings \\(uncertainty_halt\\)"):
        _check_resume(
            {"config": older},
            MBPOConfig(imagination=ImaginationOptions(episode_steps=250, uncertainty_halt=0.06)),
            tmp_path / "mbpo.json",
        )


def test_mbpo_reads_the_imagination_options_of_old_and_new_run_folders():
    from rwm_gym.rl.mbpo import MBPOConfig

    flat = {
        "iterations": 2,
        "imagined_episode_steps": 50,
        "uncertainty_halt": 0.06,
        "fall_tilt": 30.0,
        "torque_halt": 0.95,
        "random_first_episode_length": True,
        "trust_entry_points": False,
    }
    config = MBPOConfig.from_dict(flat)
    assert config.iterations == 2
    assert config.imagination == ImaginationOptions(
        episode_steps=50, uncertainty_halt=0.06, fall_tilt=30.0, torque_halt=0.95, random_first_episode_length=True
    )
    assert MBPOConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config


def test_mbpo_options_come_from_its_config_fields():
    import argparse

    from rwm_gym.commands import mbpo

    parser = argparse.ArgumentParser()
    mbpo.add_arguments(parser)
    args = parser.parse_args(
        ["--data", "d.h5", "--out", "o", "--model-finetune", "--iterations", "2", "--model-lr", "3e-4"]
    )
    assert (args.model_finetune, args.iterations, args.model_lr) == (True, 2, 3e-4)
    assert parser.parse_args(["--data", "d", "--out", "o", "--no-model-finetune"]).model_finetune is False
    defaults = mbpo.config_from(parser.parse_args(["--data", "d", "--out", "o"]), {})  # flags left out: None
    assert defaults == mbpo.MBPOConfig() and not defaults.model_finetune
    assert "Fine-tune the current world model" in parser.format_help()
    assert defaults.imagination.episode_steps == 250  # the loop's own default time limit, under its old flag name too
    assert parser.parse_args(["--data", "d", "--out", "o", "--imagined-episode-steps", "50"]).episode_steps == 50


def test_a_run_dir_records_its_env_and_refuses_another_on_resume(tmp_path, capsys):
    run = tmp_path / "run"
    args = [
        "ppo",
        "--in",
        "imagination",
        "--num-envs",
        "8",
        "--n-steps",
        "8",
        "--net-arch",
        "16",
        "--threads",
        "1",
        "--run-dir",
        str(run),
        "--no-eval",
        "--out",
        str(run / "final.zip"),
        "--episode-steps",
        "20",
    ]
    assert main([*args, "--timesteps", "64"]) == 0
    state = json.loads((run / "state.json").read_text())
    assert state["env"] == {"where": "imagination", "checkpoint": None, "imagination": {"episode_steps": 20}}
    with pytest.raises(SystemExit, match="started in another env"):
        main([*args[:-1], "30", "--timesteps", "128"])
    assert main([*args, "--timesteps", "128"]) == 0  # the same env resumes
    assert json.loads((run / "state.json").read_text())["timesteps"] == 128


def test_sample_predictions_reaches_the_imagined_env_and_its_record(tmp_path):
    run = tmp_path / "run"
    args = [
        "ppo",
        "--in",
        "imagination",
        "--num-envs",
        "8",
        "--n-steps",
        "8",
        "--net-arch",
        "16",
        "--threads",
        "1",
        "--run-dir",
        str(run),
        "--no-eval",
        "--out",
        str(run / "final.zip"),
        "--timesteps",
        "64",
    ]
    assert main([*args, "--sample-predictions"]) == 0
    state = json.loads((run / "state.json").read_text())
    assert state["env"]["imagination"] == {"sample_predictions": True}
    with pytest.raises(SystemExit, match="started in another env"):  # resuming without it would change the env
        main(args)
    with pytest.raises(SystemExit, match="--sample-predictions apply to --in imagination"):
        main(["ppo", "--in", "physics", "--sample-predictions", "--timesteps", "1"])


def test_imagination_options_are_refused_in_physics_by_name():
    from rwm_gym.cli import main

    with pytest.raises(SystemExit, match="--uncertainty-halt, --random-first-episode-length apply to --in imagination"):
        main(
            ["ppo", "--in", "physics", "--uncertainty-halt", "0.1", "--random-first-episode-length", "--timesteps", "1"]
        )


def test_a_checkpoint_that_cannot_serve_the_options_is_one_line(tmp_path):
    from rwm_gym.cli import main

    with pytest.raises(SystemExit, match=r"^rwm-gym ppo: .*missing.safetensors: no such checkpoint file$"):
        main(["ppo", "--in", "imagination", "--checkpoint", str(tmp_path / "missing.safetensors"), "--timesteps", "1"])


def test_compact_policy_drops_run_state_and_keeps_the_policy(tmp_path):
    import zipfile

    import gymnasium as gym
    from stable_baselines3.common.env_util import make_vec_env

    from rwm_gym.rl.policy_file import compact_policy, save_policy

    model = PPO(
        "MlpPolicy",
        make_vec_env(lambda: gym.make("Pendulum-v1"), n_envs=64, seed=0),
        n_steps=8,
        batch_size=64,
        n_epochs=1,
        seed=0,
        device="cpu",
    )
    model.learn(total_timesteps=512)
    full = save_policy(model, tmp_path / "full.zip")
    small = compact_policy(full, tmp_path / "small.zip")
    assert small.stat().st_size < full.stat().st_size
    loaded = PPO.load(small, device="cpu")
    assert loaded._last_obs is None  # the 64 training envs' last observations are gone
    obs = np.random.default_rng(0).normal(size=(5, 3)).astype(np.float32)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])
    with pytest.raises(FileExistsError):
        compact_policy(full, small)
    with zipfile.ZipFile(tmp_path / "other.zip", "w") as archive:
        archive.writestr("other", b"{}")
    with pytest.raises(ValueError, match="not an SB3 policy zip"):
        compact_policy(tmp_path / "other.zip", tmp_path / "x.zip")


def test_annealed_fraction_falls_linearly_over_the_last_steps_to_one_rollouts_share():
    from rwm_gym.rl.ppo import annealed_fraction

    # a budget of 10 rollouts of 64 steps ending at 640, annealed over its last 320 steps
    shares = [annealed_fraction(t, 640, 320, 64) for t in range(64, 641, 64)]
    assert shares == pytest.approx([1, 1, 1, 1, 1, 1, 0.8, 0.6, 0.4, 0.2])
    assert annealed_fraction(640, 640, 0, 64) == 1.0  # no anneal
    assert annealed_fraction(704, 640, 320, 64) == pytest.approx(0.2)  # past the end: never 0 (no dead update)


def _lr_column(run) -> list[float]:
    import csv

    with (run / "log.csv").open() as f:
        return [float(row["lr"]) for row in csv.DictReader(f)]


def test_the_learning_rate_anneal_ends_with_the_budget_and_a_resumed_run_stays_on_its_line(tmp_path, monkeypatch):
    from rwm_gym.rl.training_run import RunCheckpoint

    def ppo(run, *extra):
        return main(
            [
                "ppo",
                "--in",
                "imagination",
                "--num-envs",
                "8",
                "--n-steps",
                "8",
                "--net-arch",
                "16",
                "--threads",
                "1",
                "--save-every",
                "1",
                "--run-dir",
                str(run),
                "--no-eval",
                "--out",
                str(run / "final.zip"),
                "--timesteps",
                "640",
                "--lr-anneal-fraction",
                "0.5",
                *extra,
            ]
        )

    whole, stopped = tmp_path / "whole", tmp_path / "stopped"
    assert ppo(whole) == 0
    lr = _lr_column(whole)
    assert len(lr) == 10
    # rollouts 7-10 end inside the last 320 steps: the lr of rollout 6 scaled by 0.8, 0.6, 0.4, 0.2, not adapted
    assert lr[6:] == pytest.approx([lr[5] * share for share in (0.8, 0.6, 0.4, 0.2)])

    save = RunCheckpoint.save

    def killed_after_rollout_7(self):
        save(self)
        if self._rollout_index() == 7:
            raise KeyboardInterrupt

    monkeypatch.setattr(RunCheckpoint, "save", killed_after_rollout_7)
    assert ppo(stopped) == 130  # Ctrl-C: the documented status, the resume point kept
    monkeypatch.setattr(RunCheckpoint, "save", save)
    assert ppo(stopped) == 0
    resumed = _lr_column(stopped)
    assert resumed[:7] == lr[:7] and resumed[7:] == pytest.approx(lr[7:])  # the same line from the saved lr alone
    with pytest.raises(SystemExit, match="other PPO settings"):  # the anneal is part of the run's settings
        main(
            [
                "ppo",
                "--num-envs",
                "8",
                "--n-steps",
                "8",
                "--net-arch",
                "16",
                "--run-dir",
                str(stopped),
                "--no-eval",
                "--out",
                str(stopped / "final.zip"),
                "--timesteps",
                "1280",
            ]
        )
    with pytest.raises(SystemExit, match="--lr-anneal-fraction needs a --timesteps budget"):
        main(
            [
                "ppo",
                "--num-envs",
                "8",
                "--n-steps",
                "8",
                "--minutes",
                "0.1",
                "--lr-anneal-fraction",
                "0.5",
                "--no-eval",
                "--out",
                str(tmp_path / "p.zip"),
            ]
        )


def test_a_run_dir_from_before_the_anneal_resumes_with_its_default(tmp_path):
    run = tmp_path / "run"
    args = [
        "ppo",
        "--num-envs",
        "8",
        "--n-steps",
        "8",
        "--net-arch",
        "16",
        "--threads",
        "1",
        "--run-dir",
        str(run),
        "--no-eval",
        "--out",
        str(run / "final.zip"),
    ]
    assert main([*args, "--timesteps", "64"]) == 0
    state = json.loads((run / "state.json").read_text())
    del state["ppo"]["lr_anneal_fraction"]  # as written before the field existed
    (run / "state.json").write_text(json.dumps(state))
    assert main([*args, "--timesteps", "128"]) == 0
    assert json.loads((run / "state.json").read_text())["timesteps"] == 128


def test_state_dependent_exploration_holds_its_noise_and_saves_a_policy_that_loads(tiny_checkpoint, tmp_path):
    """gSDE (`use_sde`): within one exploration matrix the same observation gets the same noisy action (noise held in
    time, unlike white noise); the policy trains in imagination and its zip loads through the safe loader."""
    from rwm_gym.policy_zip import load_policy
    from rwm_gym.rl.ppo import save_policy

    config = replace(TINY, use_sde=True, log_std_init=-2.0)
    env = make_env("imagination", config.num_envs, checkpoint=tiny_checkpoint, seed=0, env_kwargs={"episode_steps": 16})
    model = make_ppo(env, config, seed=0)
    assert model.use_sde and model.sde_sample_freq == -1
    obs = torch.as_tensor(env.reset(), dtype=torch.float32)
    model.policy.reset_noise(config.num_envs)
    first, again = model.policy(obs)[0], model.policy(obs)[0]
    torch.testing.assert_close(first, again)
    model.policy.reset_noise(config.num_envs)
    assert not torch.allclose(first, model.policy(obs)[0])
    learn(model, timesteps=2 * config.num_envs * config.n_steps, progress=False)
    path = save_policy(model, tmp_path / "sde.zip")
    loaded = load_policy(path)
    assert loaded.use_sde
    action, _ = loaded.predict(obs.numpy(), deterministic=True)
    np.testing.assert_allclose(action, model.predict(obs.numpy(), deterministic=True)[0], atol=1e-6)


def test_bf16_updates_train_in_autocast_while_rollouts_and_heads_stay_float32(tiny_checkpoint, monkeypatch):
    """`update_precision="bfloat16"`: SB3's update runs under autocast, the rollouts and the action / value heads do
    not, and training ends with autocast off."""
    from rwm_gym.rl.ppo import update_callbacks

    config = replace(TINY, update_precision="bfloat16")
    env = make_env("imagination", config.num_envs, checkpoint=tiny_checkpoint, seed=0, env_kwargs={"episode_steps": 16})
    model = make_ppo(env, config, seed=0)
    seen = {"train": [], "collect": [], "heads": []}
    train, step_async = model.train, model.env.step_async

    def spy_train():
        seen["train"].append(torch.is_autocast_enabled("cpu"))
        obs = torch.zeros(2, env.observation_space.shape[0])
        latent_pi, latent_vf = model.policy.mlp_extractor(model.policy.extract_features(obs))
        heads = (model.policy.action_net(latent_pi), model.policy.value_net(latent_vf))
        seen["heads"].append({h.dtype for h in heads})
        train()

    def spy_step(actions):
        seen["collect"].append(torch.is_autocast_enabled("cpu"))
        step_async(actions)

    monkeypatch.setattr(model, "train", spy_train)
    monkeypatch.setattr(model.env, "step_async", spy_step)
    learn(
        model, timesteps=3 * config.num_envs * config.n_steps, progress=False, callbacks=update_callbacks(config, model)
    )
    assert seen["train"] == [True] * 3 and seen["collect"] == [False] * (3 * config.n_steps)
    assert seen["heads"] == [{torch.float32}] * 3
    assert not torch.is_autocast_enabled("cpu")
    with pytest.raises(ValueError, match="update_precision"):
        PPOConfig(update_precision="float16")
