"""Files a user can trust, tried as a user who makes mistakes would: files that carry code, outputs that would
destroy inputs or each other, and bad numbers. Each test names the case it covers; every one fails in one line
(exit 2) or not at all, and no input file changes."""

from __future__ import annotations

import base64
import errno
import json
import os
import re
import shutil
import zipfile
from pathlib import Path

import cloudpickle
import gymnasium as gym
import numpy as np
import pytest
import torch
from synthetic_dynamics import SPEC, info_for, linear_episodes, write_linear_dataset

import rwm_gym
from rwm_gym.cli import main
from rwm_gym.resources import assets_dir

SHIPPED_POLICIES = sorted((assets_dir() / "policies").glob("*.zip"))
TINY_TRAIN = [
    "--model",
    "rwm",
    "--iterations",
    "2",
    "--history",
    "4",
    "--forecast",
    "2",
    "--batch-size",
    "4",
    "--hidden-size",
    "8",
    "--num-layers",
    "1",
    "--head-hidden",
    "8",
    "--val-fraction",
    "0.25",
    "--quiet",
]


def one_line_error(capsys, *words: str) -> str:
    """The command's stderr, progress bars aside, is one line holding `words`."""
    lines = [line for line in re.split(r"[\r\n]+", capsys.readouterr().err.strip()) if not re.search(r"\d+%\|", line)]
    err = "\n".join(lines)
    assert len(lines) == 1 and "Traceback" not in err, err
    for word in words:
        assert word in err, err
    return err


class _RunsCode:
    """What an attacker puts in a file: unpickling it calls os.system."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"echo ran > {self.marker}",)


def malicious_zip(folder: Path, key: str = "lr_schedule") -> tuple[Path, Path]:
    """A shipped policy whose `key` entry runs a shell command when SB3 unpickles it; returns (zip, marker)."""
    marker, evil = folder / "pwned.txt", folder / "evil.zip"
    with zipfile.ZipFile(SHIPPED_POLICIES[0]) as src, zipfile.ZipFile(evil, "w") as out:
        for info in src.infolist():
            payload = src.read(info)
            if info.filename == "data":
                data = json.loads(payload)
                data[key] = {
                    ":type:": "<class 'object'>",
                    ":serialized:": base64.b64encode(cloudpickle.dumps(_RunsCode(marker))).decode(),
                }
                payload = json.dumps(data).encode()
            out.writestr(info, payload)
    return evil, marker


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_linear_dataset(tmp_path_factory.mktemp("data") / "linear.h5", num_episodes=6)


@pytest.fixture(scope="module")
def checkpoint(data: Path, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ckpt") / "m.safetensors"
    assert main(["train", "--data", str(data), "--out", str(out), *TINY_TRAIN]) == 0
    return out


# X1: policy zips ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("key", ["lr_schedule", "observation_space", "policy_kwargs"])
def test_a_malicious_policy_zip_runs_nothing_through_any_loader(tmp_path: Path, key: str) -> None:
    from rwm_gym.policies.factory import make_policy
    from rwm_gym.policy_zip import PolicyFileError, load_policy
    from rwm_gym.rl.evaluate_policy import as_policy

    evil, marker = malicious_zip(tmp_path, key)
    for load in (load_policy, as_policy, lambda p: make_policy(str(p), SPEC, 1)):
        with pytest.raises(PolicyFileError, match=f"entry '{key}' is <class 'object'>") as err:
            load(evil)
        assert "\n" not in str(err.value)
    assert not marker.exists()


@pytest.mark.parametrize(
    "command",
    [
        ["score", "--policy", "{evil}", "--out", "{tmp}/score", "--seeds", "1", "--commands", "0", "--steps", "2"],
        [
            "collect",
            "--policy",
            "{evil}",
            "--out",
            "{tmp}/d.h5",
            "--episodes",
            "1",
            "--max-steps",
            "2",
            "--num-envs",
            "1",
        ],
        ["make-measured", "--policy", "{evil}", "--out", "{tmp}/m.h5", "--episodes", "1", "--max-steps", "2"],
    ],
)
def test_commands_given_a_malicious_policy_zip_fail_in_one_line_and_run_nothing(
    tmp_path: Path, capsys, command
) -> None:
    evil, marker = malicious_zip(tmp_path)
    assert main([c.format(evil=evil, tmp=tmp_path) for c in command]) == 2
    one_line_error(capsys, "lr_schedule")
    assert not marker.exists()


def test_no_module_loads_sb3_zips_any_other_way() -> None:
    """mbpo --init-policy, ppo's resume and --keep-best, ...: every load goes through the safe loader."""
    package = Path(rwm_gym.__file__).parent
    offenders = [
        str(p.relative_to(package))
        for p in package.rglob("*.py")
        if p.name != "policy_zip.py" and "PPO.load(" in p.read_text().replace("`PPO.load(", "")
    ]
    assert offenders == []


@pytest.mark.parametrize("policy", SHIPPED_POLICIES, ids=lambda p: p.name)
def test_every_shipped_policy_loads_safely_and_acts_as_sb3_loads_it(policy: Path) -> None:
    from stable_baselines3 import PPO

    from rwm_gym.policy_zip import load_policy
    from rwm_gym.spec import load_spec

    safe, plain = load_policy(policy, spec=load_spec("anymal_d")), PPO.load(policy, device="cpu")
    obs = np.random.default_rng(0).normal(size=(64, *plain.observation_space.shape)).astype(np.float32)
    np.testing.assert_array_equal(safe.predict(obs, deterministic=True)[0], plain.predict(obs, deterministic=True)[0])
    assert safe.observation_space == plain.observation_space and safe.action_space == plain.action_space
    assert safe.lr_schedule(0.5) == plain.lr_schedule(0.5) and safe.clip_range(0.5) == plain.clip_range(0.5)
    assert safe.policy_kwargs.keys() == plain.policy_kwargs.keys()


def test_a_training_run_zip_with_its_run_state_loads_safely(tmp_path: Path) -> None:
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    from rwm_gym.policy_zip import load_policy

    model = PPO(
        "MlpPolicy", make_vec_env("Pendulum-v1", n_envs=2), n_steps=128, batch_size=64, n_epochs=1, device="cpu"
    )
    model.learn(512)
    model.save(tmp_path / "p.zip")
    loaded = load_policy(tmp_path / "p.zip")  # the run state is pickled: ignored, training goes on from env resets
    assert loaded._last_obs is None and loaded.num_timesteps == model.num_timesteps
    obs = np.random.default_rng(0).normal(size=(16, 3)).astype(np.float32)
    np.testing.assert_array_equal(loaded.predict(obs, deterministic=True)[0], model.predict(obs, deterministic=True)[0])


def _pendulum_policy(path: Path) -> Path:
    from stable_baselines3 import PPO

    PPO("MlpPolicy", "Pendulum-v1", n_steps=64, device="cpu").save(path)
    return path


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda folder: (folder / "p.zip").write_text("not a zip") and folder / "p.zip", ["not a readable"]),
        (
            lambda folder: (folder / "p.zip").write_bytes(SHIPPED_POLICIES[0].read_bytes()[:3000]) and folder / "p.zip",
            ["not a readable"],
        ),
        (lambda folder: _pendulum_policy(folder / "p.zip"), ["observations (3,)", "(48,)"]),
    ],
)
def test_policy_files_that_are_not_anymal_policies_fail_in_one_line(tmp_path: Path, capsys, make, words) -> None:
    policy = make(tmp_path)
    assert (
        main(
            [
                "collect",
                "--policy",
                str(policy),
                "--out",
                str(tmp_path / "d.h5"),
                "--episodes",
                "1",
                "--max-steps",
                "2",
                "--num-envs",
                "1",
            ]
        )
        == 2
    )
    one_line_error(capsys, *words)
    assert (
        main(
            [
                "score",
                "--policy",
                str(policy),
                "--out",
                str(tmp_path / "s"),
                "--seeds",
                "1",
                "--commands",
                "0",
                "--steps",
                "2",
            ]
        )
        == 2
    )
    one_line_error(capsys, *words)


# X2: entry points carried by files -----------------------------------------------------------------------------------


@pytest.fixture
def entry_point_checkpoint(tmp_path: Path, monkeypatch) -> tuple[Path, Path, Path]:
    """(checkpoint, its data, marker): the data's spec names `planted:reward`, a module that writes the marker
    when imported, found on sys.path as a module in the working directory would be."""
    marker = tmp_path / "imported.txt"
    (tmp_path / "planted.py").write_text(
        f"open({str(marker)!r}, 'w').write('ran')\ndef reward(t):\n    return t.next_state[:, 0] * 0\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    spec_text = SPEC.text + '\n[imagination]\nreward = "planted:reward"\n'
    from rwm_gym.data.dataset import write_dataset
    from rwm_gym.spec import parse_spec

    spec = parse_spec(spec_text)
    data = tmp_path / "d.h5"
    write_dataset(data, info_for(spec), linear_episodes(num_episodes=6, spec=spec))
    out = tmp_path / "m.safetensors"
    assert main(["train", "--data", str(data), "--out", str(out), *TINY_TRAIN]) == 0  # training imports nothing
    assert not marker.exists()
    return out, data, marker


def test_a_checkpoint_naming_an_entry_point_imports_nothing_unless_trusted(entry_point_checkpoint) -> None:
    checkpoint, data, marker = entry_point_checkpoint
    with pytest.raises(ValueError, match="module 'planted'") as err:
        gym.make("rwm_gym:Imagined-v0", checkpoint=str(checkpoint), reset_data=str(data))
    assert "\n" not in str(err.value) and "trust_entry_points=True" in str(err.value)
    assert not marker.exists()

    def mine(t):
        return np.zeros(len(t.next_state))

    env = gym.make("rwm_gym:Imagined-v0", checkpoint=str(checkpoint), reset_data=str(data), reward_fn=mine)
    env.reset(seed=0)
    env.step(env.action_space.sample())
    assert not marker.exists()
    gym.make("rwm_gym:Imagined-v0", checkpoint=str(checkpoint), reset_data=str(data), trust_entry_points=True)
    assert marker.exists()  # the user's explicit choice


def test_ppo_on_a_checkpoint_naming_an_entry_point_refuses_it_in_one_line(entry_point_checkpoint, capsys) -> None:
    checkpoint, data, marker = entry_point_checkpoint
    with pytest.raises(SystemExit) as stop:
        main(
            [
                "ppo",
                "--checkpoint",
                str(checkpoint),
                "--reset-data",
                str(data),
                "--timesteps",
                "64",
                "--out",
                str(checkpoint.with_name("p.zip")),
                "--no-eval",
            ]
        )
    assert "module 'planted'" in str(stop.value) and "--trust-entry-points" in str(stop.value)
    assert not marker.exists()


# Outputs never clobber inputs or each other ------------------------------------------------------------------------


def _collect(out: Path, *extra: str) -> list[str]:
    return [
        "collect",
        "--policy",
        "zero",
        "--episodes",
        "1",
        "--max-steps",
        "3",
        "--num-envs",
        "1",
        "--out",
        str(out),
        *extra,
    ]


def test_l1_a_failed_collect_overwrite_keeps_the_good_file(tmp_path: Path, capsys, monkeypatch) -> None:
    from rwm_gym.data.dataset import DatasetWriter

    out = tmp_path / "d.h5"
    assert main(_collect(out)) == 0
    before, _ = out.read_bytes(), capsys.readouterr()
    assert main(_collect(out, "--overwrite", "--physics", '{"kp_scale": NaN}')) == 2
    one_line_error(capsys, "NaN")
    assert out.read_bytes() == before

    def disk_full(self, episode):  # the full disk: the episode's write fails
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(DatasetWriter, "append_episode", disk_full)
    assert main(_collect(out, "--overwrite")) == 2
    one_line_error(capsys, "No space left on device")
    assert out.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.h5"]  # no partial or lock file left


def test_collect_stops_in_one_line_before_hdf5_runs_out_of_space(tmp_path: Path, capsys, monkeypatch) -> None:
    """HDF5 that hits a full disk mid-write crashed the process (SIGSEGV, on a real 600 KB tmpfs): the writer checks
    the free space before each episode, and the episodes finished before it stay."""
    calls = []

    def disk_usage(path):  # room for two episodes
        calls.append(path)
        return shutil._ntuple_diskusage(10**9, 10**9, 10**9 if len(calls) <= 2 else 1000)

    monkeypatch.setattr(shutil, "disk_usage", disk_usage)
    out = tmp_path / "d.h5"
    assert main(_collect(out, "--episodes", "4")) == 2
    one_line_error(capsys, "No space left on device", "episode 2")
    from rwm_gym.data.dataset import Dataset

    kept = Dataset.load(out)
    assert kept.num_episodes == 2 and not kept.info.complete


def test_l2_train_refuses_its_dataset_as_out(data: Path, tmp_path: Path, capsys) -> None:
    copy = str(shutil.copy(data, tmp_path / "d.h5"))
    before = Path(copy).read_bytes()
    assert main(["train", "--data", copy, "--out", copy, "--overwrite", *TINY_TRAIN]) == 2
    one_line_error(capsys, "is the input")
    assert Path(copy).read_bytes() == before


def test_l3_l4_ppo_refuses_its_checkpoint_as_out_and_an_existing_out(checkpoint: Path, tmp_path: Path, capsys) -> None:
    model = Path(shutil.copy(checkpoint, tmp_path / "m.safetensors"))
    before = model.read_bytes()
    with pytest.raises(SystemExit) as stop:
        main(["ppo", "--checkpoint", str(model), "--out", str(model), "--timesteps", "64", "--no-eval"])
    assert "is the input" in str(stop.value) and model.read_bytes() == before
    existing = tmp_path / "p.zip"
    existing.write_bytes(b"a policy of hours")
    with pytest.raises(SystemExit) as stop:
        main(["ppo", "--in", "physics", "--out", str(existing), "--timesteps", "64", "--no-eval"])
    assert "--overwrite" in str(stop.value) and existing.read_bytes() == b"a policy of hours"


def test_l5_import_refuses_an_out_inside_the_minari_folder(data: Path, tmp_path: Path, capsys) -> None:
    pytest.importorskip("minari")
    folder = tmp_path / "mx"
    assert main(["export", "--minari", str(data), "--out", str(folder)]) == 0
    inside = next(folder.rglob("main_data.hdf5"))
    before = inside.read_bytes()
    assert main(["import", "--minari", str(folder), "--out", str(inside), "--overwrite"]) == 2
    one_line_error(capsys, "is inside the input")
    assert inside.read_bytes() == before


def test_export_with_a_relative_out_as_in_the_readme(data: Path, tmp_path: Path, monkeypatch) -> None:
    pytest.importorskip("minari")
    monkeypatch.chdir(tmp_path)
    assert main(["export", "--minari", str(data), "--out", "mx3"]) == 0
    assert main(["import", "--minari", "mx3", "--out", "back.h5"]) == 0
    assert not list(tmp_path.glob(".mx3*"))


@pytest.mark.parametrize("command", ["collect", "train"])
def test_l6_l7_a_second_writer_of_the_same_out_fails_at_once(data: Path, tmp_path: Path, capsys, command) -> None:
    """Another process holds the output's lock (a second open file description conflicts as a process would)."""
    from rwm_gym.output_guard import _lock, lock_path, resolved

    out = tmp_path / ("d.h5" if command == "collect" else "m.safetensors")
    fd = _lock(lock_path(resolved(out)), out)
    try:
        argv = _collect(out) if command == "collect" else ["train", "--data", str(data), "--out", str(out), *TINY_TRAIN]
        assert main(argv) == 2
        one_line_error(capsys, "being written by another run")
        assert not out.exists()
    finally:
        os.close(fd)
    assert main(argv) == 0  # the lock goes with its holder


def test_orphaned_temp_files_are_removed_by_the_next_write(tmp_path: Path) -> None:
    from rwm_gym.atomic import write_text
    from rwm_gym.data.dataset import DatasetWriter

    (tmp_path / ".r.json.abc123.tmp").write_text("half")
    (tmp_path / "d.h5.partial-0badc0de").write_text("half")
    write_text(tmp_path / "r.json", "{}")
    with DatasetWriter(tmp_path / "d.h5", info_for()) as writer:
        writer.append_episode(linear_episodes(num_episodes=1)[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.h5", "r.json"]


@pytest.mark.parametrize("out", ["{tmp}/a_file/m.safetensors", "{tmp}"])
def test_unwritable_or_odd_outs_fail_before_the_run_in_one_line(
    data: Path, tmp_path: Path, capsys, monkeypatch, out
) -> None:
    import rwm_gym.commands.train as train_command

    (tmp_path / "a_file").write_text("")
    monkeypatch.setattr(train_command, "train", lambda *a, **k: pytest.fail("the run started"))
    assert main(["train", "--data", str(data), "--out", out.format(tmp=tmp_path), "--overwrite", *TINY_TRAIN]) == 2
    one_line_error(capsys, "--out")
    with pytest.raises(SystemExit) as stop:
        main(["score", "--policy", "zero", "--out", str(tmp_path / "a_file"), "--steps", "2"])
    assert "is a file" in str(stop.value)


def test_a_full_disk_while_saving_a_checkpoint_is_one_line(data: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    import rwm_gym.model.checkpoint as checkpoint_module

    def disk_full(tensors, path, metadata=None):
        Path(path).write_bytes(b"half")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(checkpoint_module, "save_file", disk_full)
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "m.safetensors"), *TINY_TRAIN]) == 2
    one_line_error(capsys, "No space left on device")
    assert list(tmp_path.iterdir()) == []


# Fail early and in one line ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv",
    [
        ["ppo", "--timesteps", "-100"],
        ["ppo", "--minutes", "-1"],
        ["ppo", "--minutes", "nan"],
        ["mbpo", "--data", "d.h5", "--out", "r", "--iterations", "-2"],
        ["collect", "--out", "d.h5", "--action-noise", "nan"],
        ["collect", "--out", "d.h5", "--action-noise", "-1"],
    ],
)
def test_bad_counts_and_amounts_are_refused_by_the_parser(argv, capsys, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)  # were an option let through, its run writes here
    assert main(argv) == 2
    assert "must be >" in capsys.readouterr().err.strip().splitlines()[-1]


def test_ppo_with_a_zero_budget_trains_nothing_and_says_so(tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["ppo", "--in", "physics", "--timesteps", "0", "--out", str(tmp_path / "p.zip")])
    assert "trains nothing" in str(stop.value) and not (tmp_path / "p.zip").exists()


@pytest.mark.parametrize("physics", ['{"payload_mass": NaN}', '{"kp_scale": Infinity}'])
def test_collect_refuses_non_finite_physics(tmp_path: Path, capsys, physics: str) -> None:
    assert main(_collect(tmp_path / "d.h5", "--physics", physics)) == 2
    one_line_error(capsys)
    assert not (tmp_path / "d.h5").exists()
    with pytest.raises(ValueError, match="finite"):
        from rwm_gym.physics.params import PhysicsParams

        PhysicsParams(payload_mass=float("nan"))


def test_evaluate_says_which_horizons_are_past_its_episodes_and_reports_the_rest(
    checkpoint: Path, data: Path, tmp_path: Path, capsys
) -> None:
    out = tmp_path / "eval"
    args = ["evaluate", "--checkpoint", str(checkpoint), "--data", str(data), "--horizons", "8", "100000"]
    assert main([*args, "--out", str(out), "--quiet"]) == 0
    said = capsys.readouterr().err.strip().splitlines()
    assert len(said) == 1 and "horizons [100000] are longer than its evaluated episodes allow" in said[0]
    assert 8 in json.loads((out / "evaluation.json").read_text())["horizons"]


@pytest.mark.parametrize("damage", ["nan weight", "zero std"])
def test_a_checkpoint_with_nan_weights_or_zero_std_is_refused_at_load(
    checkpoint: Path, tmp_path: Path, damage: str
) -> None:
    from safetensors import safe_open
    from safetensors.torch import save_file

    from rwm_gym.model.checkpoint import CheckpointError, load_checkpoint

    with safe_open(checkpoint, "pt") as f:
        tensors, meta = {k: f.get_tensor(k) for k in f.keys()}, f.metadata()
    name = next(k for k in tensors if k.startswith("model/")) if damage == "nan weight" else "norm/state_std"
    tensors[name] = torch.full_like(tensors[name], float("nan") if damage == "nan weight" else 0.0)
    save_file(tensors, tmp_path / "bad.safetensors", metadata=meta)
    with pytest.raises(CheckpointError, match="NaN or inf" if damage == "nan weight" else "std > 0"):
        load_checkpoint(tmp_path / "bad.safetensors")


def test_train_resume_without_a_file_is_an_error(data: Path, tmp_path: Path, capsys) -> None:
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "m.safetensors"), "--resume", *TINY_TRAIN]) == 2
    one_line_error(capsys, "nothing to resume")


@pytest.mark.parametrize("option", [["--hidden-size", "100000"], ["--batch-size", str(10**7)]])
def test_a_model_too_big_for_the_machine_is_refused_before_allocating(
    data: Path, tmp_path: Path, capsys, monkeypatch, option
) -> None:
    import rwm_gym.commands.train as train_command

    monkeypatch.setattr(train_command, "train", lambda *a, **k: pytest.fail("the run started"))  # never allocate
    argv = ["train", "--data", str(data), "--out", str(tmp_path / "m.safetensors"), *TINY_TRAIN, *option]
    assert main(argv) == 2  # the last of a repeated option wins
    one_line_error(capsys, "GiB")


def test_complex_actions_are_refused() -> None:
    from rwm_gym.batched_core import check_actions

    with pytest.raises(ValueError, match="complex"):
        check_actions(np.full((1, 12), 0.5 + 0.5j), (1, 12))
