"""The robot as a flag (`--physics`): parsed once for every command, scored on, trained on, and fine-tuned from a
given policy (`--init-policy`)."""

import json

import numpy as np
import pytest
import torch

from rwm_gym.cli import main
from rwm_gym.commands._options import parse_physics
from rwm_gym.rl.policy_file import save_policy
from rwm_gym.rl.ppo import PPOConfig, make_env, make_ppo, start_from

TINY = PPOConfig(num_envs=4, n_steps=8, net_arch=(16, 16), num_minibatches=2, n_epochs=1)


def test_physics_comes_as_json_or_as_a_file_and_corrected_physics_is_unwrapped(tmp_path):
    assert parse_physics('{"payload_mass": 5.0}') == {"payload_mass": 5.0}
    corrected = tmp_path / "corrected_physics.json"
    corrected.write_text(json.dumps({"physics": {"ground_friction": 0.5, "action_delay": 0.02}}))
    assert parse_physics(str(corrected)) == {"ground_friction": 0.5, "action_delay": 0.02}
    bare = tmp_path / "robot.json"
    bare.write_text('{"motor_strength": [0.5, 0.5, 0.5, 1, 1, 1, 1, 1, 1, 1, 1, 1]}')
    assert parse_physics(str(bare))["motor_strength"][0] == 0.5


@pytest.mark.parametrize(
    "text, message",
    [
        ("{bad", "--physics is not valid JSON"),
        ('{"payload_mas": 5}', "unknown physics parameter(s) ['payload_mas']"),
        ('{"payload_mass": NaN}', "NaN is not a physics value"),
        ('{"payload_mass": "heavy"}', "must be a finite number"),
        ("[1, 2]", "must be a JSON object"),
    ],
)
def test_bad_physics_is_one_line_naming_the_flag(text, message):
    with pytest.raises(ValueError) as err:
        parse_physics(text)
    assert message in str(err.value) and str(err.value).startswith("--physics") and "\n" not in str(err.value)


def test_a_bad_physics_file_is_named(tmp_path):
    robot = tmp_path / "robot.json"
    robot.write_text("{nope")
    with pytest.raises(ValueError, match=f"--physics {robot} is not valid JSON"):
        parse_physics(str(robot))


def test_score_runs_on_the_given_robot_and_records_it(tmp_path, capsys):
    common = ["score", "--policy", "gait", "--seeds", "1", "--commands", "0", "--steps", "60"]
    assert main([*common, "--out", str(tmp_path / "nominal")]) == 0
    heavy = '{"payload_mass": 40.0, "ground_friction": 0.3}'
    assert main([*common, "--physics", heavy, "--out", str(tmp_path / "heavy")]) == 0
    nominal = json.loads((tmp_path / "nominal" / "score.json").read_text())
    changed = json.loads((tmp_path / "heavy" / "score.json").read_text())
    assert nominal["physics"] is None and changed["physics"] == {"payload_mass": 40.0, "ground_friction": 0.3}
    assert "payload_mass=40.0" in changed["where"]
    assert changed["evaluation"]["commands"] != nominal["evaluation"]["commands"]  # another robot moved


def test_score_refuses_physics_in_a_world_model_and_bad_physics_in_one_line(tmp_path):
    with pytest.raises(SystemExit, match="--physics sets the robot in physics"):
        main(["score", "--policy", "zero", "--checkpoint", "x.safetensors", "--physics", "{}", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match=r"rwm-gym score: --physics: unknown physics parameter\(s\) \['mass'\]"):
        main(["score", "--policy", "zero", "--physics", '{"mass": 1}', "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o").exists()


def test_start_from_copies_the_whole_network_and_refuses_another_shape(tmp_path):
    source = make_ppo(make_env("physics", TINY.num_envs, seed=0), TINY, seed=1)
    with torch.no_grad():
        source.policy.log_std.fill_(-0.7)
    path = save_policy(source, tmp_path / "source.zip")
    target = make_ppo(make_env("physics", TINY.num_envs, seed=0), TINY, seed=2)
    assert not torch.equal(next(target.policy.parameters()), next(source.policy.parameters()))
    start_from(target, path)
    for name, value in source.policy.state_dict().items():
        assert torch.equal(target.policy.state_dict()[name], value), name
    wider = PPOConfig(**{**TINY.to_dict(), "net_arch": (32, 16)})
    other = make_ppo(make_env("physics", TINY.num_envs, seed=0), wider, seed=0)
    with pytest.raises(ValueError, match="its network does not fit this policy's"):
        start_from(other, path)


def _ppo(tmp_path, *extra):
    return [
        "ppo",
        "--in",
        "physics",
        "--timesteps",
        "64",
        "--num-envs",
        "4",
        "--n-steps",
        "16",
        "--net-arch",
        "16",
        "16",
        "--eval-seeds",
        "1",
        "--eval-steps",
        "10",
        "--threads",
        "1",
        *extra,
    ]


def test_ppo_fine_tunes_a_given_policy_on_the_given_robot(tmp_path, capsys):
    first = tmp_path / "first.zip"
    assert main(_ppo(tmp_path, "--out", str(first))) == 0
    robot = tmp_path / "corrected_physics.json"
    robot.write_text(json.dumps({"physics": {"payload_mass": 8.0}}))
    tuned = tmp_path / "tuned.zip"
    assert main(_ppo(tmp_path, "--physics", str(robot), "--init-policy", str(first), "--out", str(tuned))) == 0
    assert f"starting from the network of {first}" in capsys.readouterr().out
    report = json.loads(tuned.with_suffix(".json").read_text())
    assert report["physics"] == {"payload_mass": 8.0} and report["init_policy"] == str(first)
    # the judge ran on the robot trained on: the same policy scores otherwise on the nominal one
    from rwm_gym.rl.evaluate_policy import evaluate_policy

    nominal = evaluate_policy(str(tuned), seeds=[0], steps=10)
    assert not np.isclose(nominal.tracking, report["evaluation"]["tracking"])
    heavy = evaluate_policy(str(tuned), seeds=[0], steps=10, env_kwargs={"physics": {"payload_mass": 8.0}})
    assert np.isclose(heavy.tracking, report["evaluation"]["tracking"])


def test_ppo_refuses_physics_in_imagination_and_two_starting_actors(tmp_path):
    with pytest.raises(SystemExit, match="--physics applies to --in physics"):
        main(["ppo", "--physics", "{}", "--timesteps", "64", "--out", str(tmp_path / "p.zip")])
    with pytest.raises(SystemExit, match="--init-policy and --bc-data both set the starting actor"):
        main(_ppo(tmp_path, "--init-policy", "a.zip", "--bc-data", "b.h5", "--out", str(tmp_path / "p.zip")))
    with pytest.raises(SystemExit, match=r"rwm-gym ppo: --physics: unknown physics parameter"):
        main(_ppo(tmp_path, "--physics", '{"mass": 1}', "--out", str(tmp_path / "p.zip")))
    assert not (tmp_path / "p.zip").exists()


def test_a_cloned_actor_is_judged_on_the_robot_ppo_trains_on(tmp_path):
    """`--bc-data` with `--in physics --physics`: the clone's own evaluation (which `--keep-best` compares with PPO's)
    runs on the given robot, not on the nominal one."""
    data = tmp_path / "gait.h5"
    assert main(["collect", "--policy", "gait", "--episodes", "1", "--max-steps", "40", "--out", str(data)]) == 0
    heavy = {"payload_mass": 30.0}
    out = tmp_path / "clone.zip"
    args = _ppo(tmp_path, "--physics", json.dumps(heavy), "--bc-data", str(data), "--bc-steps", "20", "--out", str(out))
    assert main([*args[: args.index("--timesteps")], "--timesteps", "0", *args[args.index("--timesteps") + 2 :]]) == 0
    report = json.loads(out.with_suffix(".json").read_text())
    cloned = report["behaviour_cloning"]["evaluation"]
    assert cloned["tracking"] == report["evaluation"]["tracking"]  # no PPO step: the same actor on the same robot
    from rwm_gym.rl.evaluate_policy import evaluate_policy

    nominal = evaluate_policy(str(out), seeds=[0], steps=10)
    assert not np.isclose(nominal.tracking, cloned["tracking"])


def test_a_resumable_run_is_judged_and_reported_like_a_single_one(tmp_path):
    """`--run-dir`: the finished policy is judged in physics on the robot trained on, and the report lies beside it."""
    run, out = tmp_path / "run", tmp_path / "run" / "final.zip"
    heavy = {"payload_mass": 30.0}
    assert main(_ppo(tmp_path, "--physics", json.dumps(heavy), "--run-dir", str(run), "--out", str(out))) == 0
    report = json.loads(out.with_suffix(".json").read_text())
    assert report["physics"] == heavy and report["run_dir"] == str(run)
    assert report["train"]["timesteps"] == 64 and report["physics_samples"] == 64
    from rwm_gym.rl.evaluate_policy import evaluate_policy

    again = evaluate_policy(str(out), seeds=[0], steps=10, env_kwargs={"physics": heavy})
    assert np.isclose(again.tracking, report["evaluation"]["tracking"])
    with pytest.raises(SystemExit, match="--bc-data warm-starts a run without --run-dir"):
        main(_ppo(tmp_path, "--run-dir", str(run), "--bc-data", "d.h5", "--out", str(tmp_path / "p.zip")))
