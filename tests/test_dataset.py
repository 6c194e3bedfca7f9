"""The HDF5 dataset format: round trip, slicing, splits, and one-line errors on every kind of bad file."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

import rwm_gym
from rwm_gym.data.dataset import (
    FORMAT_NAME,
    FORMAT_VERSION,
    REQUIRED_FIELDS,
    Dataset,
    DatasetError,
    DatasetInfo,
    DatasetWriter,
    is_merge_of,
    merge_datasets,
    write_dataset,
)
from rwm_gym.spec import load_spec

SPEC = load_spec("anymal_d")
NQ, NV = 19, 18


def make_info(**changes) -> DatasetInfo:
    info = DatasetInfo(
        env_id=SPEC.physics_env_id,
        spec_text=SPEC.text,
        dt=SPEC.policy_dt,
        columns={
            "state": list(SPEC.state_columns),
            "action": list(SPEC.actuator.joints),
            "contact": list(SPEC.privileged.contact_bodies),
            "foot_height": list(SPEC.privileged.feet),
            "command": list(SPEC.command.names),
        },
        policy="random uniform",
        seed=7,
        physics_params={"friction": 0.8, "base_mass_kg": 50.0},
        metadata={"note": "test", "nested": {"a": [1, 2]}},
    )
    return DatasetInfo(**{**info.__dict__, **changes})


def make_episode(rng: np.random.Generator, transitions: int, extra: bool = False) -> dict[str, np.ndarray]:
    rows = transitions + 1
    ep = {
        "state": rng.normal(size=(rows, SPEC.state_dim)).astype(np.float32),
        "action": rng.uniform(-1, 1, size=(rows, SPEC.action_dim)).astype(np.float32),
        "contact": rng.random((rows, SPEC.contact_dim)) < 0.5,
        "foot_height": rng.random((rows, SPEC.foot_dim)).astype(np.float32),
        "terminated": np.zeros(rows, bool),
        "truncated": np.zeros(rows, bool),
        "command": rng.normal(size=(rows, len(SPEC.command.names))).astype(np.float32),
        "reward": rng.normal(size=rows).astype(np.float32),
        "qpos": rng.normal(size=(rows, NQ)),
        "qvel": rng.normal(size=(rows, NV)),
    }
    ep["action"][-1] = 0
    ep["reward"][-1] = 0
    ep["truncated"][-1] = True
    if extra:
        ep["torque"] = rng.normal(size=(rows, 3, 4)).astype(np.float16)
    return ep


@pytest.fixture
def episodes() -> list[dict[str, np.ndarray]]:
    rng = np.random.default_rng(0)
    return [make_episode(rng, n, extra=True) for n in (5, 1, 9, 3, 7, 4)]


@pytest.fixture
def path(tmp_path: Path, episodes) -> Path:
    out = tmp_path / "data.h5"
    write_dataset(out, make_info(), episodes)
    return out


def test_round_trip_every_field_and_attribute(path: Path, episodes) -> None:
    ds = Dataset.load(path)
    info = make_info()
    assert ds.info.spec_text == SPEC.text and ds.spec().state_dim == SPEC.state_dim
    for name in ("env_id", "dt", "columns", "policy", "seed", "physics_params", "metadata"):
        assert getattr(ds.info, name) == getattr(info, name), name
    assert ds.info.complete and ds.info.format_version == FORMAT_VERSION and ds.info.created_by
    assert set(ds.fields) == {*REQUIRED_FIELDS, "torque"}
    assert ds.num_episodes == 6 and ds.num_steps == sum(len(e["state"]) for e in episodes)
    np.testing.assert_array_equal(ds.episode_lengths, [6, 2, 10, 4, 8, 5])
    np.testing.assert_array_equal(ds.episode_starts, [0, 6, 8, 18, 22, 30])
    for name in ds.fields:
        expected = np.concatenate([e[name] for e in episodes])
        assert ds[name].dtype == expected.dtype and ds[name].shape == expected.shape, name
        np.testing.assert_array_equal(ds[name], expected)
    with h5py.File(path, "r") as f:
        assert f.attrs["format"] == FORMAT_NAME


def test_zero_width_fields(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    eps = [make_episode(rng, n) for n in (3, 2)]
    for ep in eps:
        ep["foot_height"] = ep["foot_height"][:, :0]
        ep["command"] = ep["command"][:, :0]
    info = make_info(columns={**make_info().columns, "foot_height": [], "command": []})
    write_dataset(tmp_path / "z.h5", info, eps)
    ds = Dataset.load(tmp_path / "z.h5")
    assert ds["foot_height"].shape == (7, 0) and ds["command"].shape == (7, 0) and ds.info.columns["command"] == []
    np.testing.assert_array_equal(ds.episode(1)["state"], eps[1]["state"])


def test_episode_slicing(path: Path, episodes) -> None:
    ds = Dataset.load(path)
    for i, ep in enumerate(episodes):
        got = ds.episode(i)
        assert set(got) == set(ep)
        for name in ep:
            np.testing.assert_array_equal(got[name], ep[name])
    np.testing.assert_array_equal(ds.episode(-1)["qpos"], episodes[-1]["qpos"])
    with pytest.raises(IndexError):
        ds.episode(6)


def test_split_by_episode(path: Path) -> None:
    ds = Dataset.load(path)
    train, val = ds.split_episodes(0.34, seed=3)
    assert len(val) == 2 and len(train) == 4
    assert not set(train) & set(val) and sorted([*train, *val]) == list(range(6))
    again = ds.split_episodes(0.34, seed=3)
    np.testing.assert_array_equal(again[0], train)
    np.testing.assert_array_equal(again[1], val)
    splits = {tuple(ds.split_episodes(0.34, seed=s)[1]) for s in range(20)}
    assert len(splits) > 1  # the seed matters
    assert len(ds.split_episodes(0.01, seed=0)[1]) == 1  # never an empty validation set when asked for one
    assert len(ds.split_episodes(0.0, seed=0)[1]) == 0


def test_merge(tmp_path: Path, path: Path, episodes) -> None:
    other = tmp_path / "other.h5"
    rng = np.random.default_rng(1)
    more = [make_episode(rng, 2, extra=True) for _ in range(2)]
    write_dataset(other, make_info(policy="ppo", physics_params={"friction": 1.0}), more)
    out = tmp_path / "merged.h5"
    merge_datasets([path, other], out)
    ds = Dataset.load(out)
    assert ds.num_episodes == 8 and ds.info.policy == "random uniform + ppo" and ds.info.physics_params == {}
    assert [s["episodes"] for s in ds.info.metadata["merged_from"]] == [6, 2]
    np.testing.assert_array_equal(ds.episode(7)["state"], more[1]["state"])
    assert is_merge_of(out, [path, other])
    assert not is_merge_of(out, [other, path]) and not is_merge_of(out, [path])
    assert not is_merge_of(tmp_path / "absent.h5", [path, other]) and not is_merge_of(path, [path])
    write_dataset(other, make_info(policy="ppo"), more[:1])  # a source that changed since
    assert not is_merge_of(out, [path, other])
    bad = tmp_path / "bad.h5"
    write_dataset(bad, make_info(spec_text=SPEC.text.replace("episode_steps = 1000", "episode_steps = 999")), more)
    with pytest.raises(DatasetError, match=r"bad.h5.*'spec'"):
        merge_datasets([path, bad], tmp_path / "never.h5")


def test_merge_ignores_file_pointers_and_drops_fields_not_in_every_file(tmp_path: Path, path: Path) -> None:
    """A PPO run's experience (extra `ppo_iteration`, a spec without `default_checkpoint` or `[symmetry]`) merges with
    collector data."""
    assert "default_checkpoint" in SPEC.text and SPEC.symmetry is not None
    rng = np.random.default_rng(2)
    ppo = [{**make_episode(rng, 3, extra=True), "ppo_iteration": np.full(4, 7, np.int32)} for _ in range(2)]
    older_spec = "\n".join(
        line for line in SPEC.text.split("\n[symmetry]")[0].splitlines() if not line.startswith("default_checkpoint")
    )
    assert "symmetry" not in older_spec
    other = tmp_path / "ppo.h5"
    write_dataset(other, make_info(spec_text=older_spec), ppo)
    out = tmp_path / "merged.h5"
    merge_datasets([path, other], out)
    merged = Dataset.load(out)
    assert merged.num_episodes == 8 and "ppo_iteration" not in merged.fields
    assert merged.info.metadata["dropped_fields"] == ["ppo_iteration"]
    np.testing.assert_array_equal(merged.episode(7)["action"], ppo[1]["action"])


def _edit(path: Path, edit) -> None:
    with h5py.File(path, "r+") as f:
        edit(f)


def _set_attr(name, value):
    return lambda f: f.attrs.__setitem__(name, value)


def _set_first_length(delta):
    def edit(f):
        f["episode_lengths"][0] += delta

    return edit


def _nan_state(f):
    f["steps/state"][3, 2] = np.nan


@pytest.mark.parametrize(
    "edit, field",
    [
        (_set_attr("format", "some-other-format"), "format"),
        (_set_attr("format_version", FORMAT_VERSION + 1), "format_version"),
        (lambda f: f["steps"].__delitem__("qvel"), "qvel"),
        (lambda f: f.attrs.__delitem__("spec"), "spec"),
        (_set_first_length(+1), "state"),  # more rows claimed than stored
        (_set_first_length(-1), "state"),  # stored rows beyond the sum in a complete file
        (_nan_state, "state"),
    ],
    ids=["format-name", "newer-version", "missing-field", "missing-attribute", "too-few-rows", "extra-rows", "nan"],
)
def test_bad_file_names_file_and_field(path: Path, edit, field: str) -> None:
    _edit(path, edit)
    with pytest.raises(DatasetError) as err:
        Dataset.load(path)
    message = str(err.value)
    assert str(path) in message and f"'{field}'" in message and "\n" not in message


def test_not_hdf5_and_truncated(tmp_path: Path, path: Path) -> None:
    text = tmp_path / "notes.h5"
    text.write_text("this is not an HDF5 file\n")
    with pytest.raises(DatasetError, match=f"{text}: file: not a readable HDF5 file"):
        Dataset.load(text)
    with pytest.raises(FileNotFoundError, match=r"absent.h5"):
        Dataset.load(tmp_path / "absent.h5")
    data = path.read_bytes()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(DatasetError, match=f"{cut}: file: .*truncated"):
        Dataset.load(cut)


def test_writer_refuses_bad_episodes_and_keeps_earlier(tmp_path: Path, episodes) -> None:
    out = tmp_path / "w.h5"
    with DatasetWriter(out, make_info()) as writer:
        writer.append_episode(episodes[0])
        writer.append_episode(episodes[1])
        bad = {**episodes[2], "state": episodes[2]["state"].copy()}
        bad["state"][1, 4] = np.nan
        with pytest.raises(DatasetError, match=r"w\.h5: field 'state': contains NaN"):
            writer.append_episode(bad)
        cases = {
            "qpos": {k: v for k, v in episodes[2].items() if k != "qpos"},  # missing
            "reward": {**episodes[2], "reward": episodes[2]["reward"][:-1]},  # length differs
            "contact": {**episodes[2], "contact": episodes[2]["contact"][:, :2]},  # width vs columns
            "qvel": {**episodes[2], "qvel": episodes[2]["qvel"][:, :5]},  # width vs earlier episodes
            "torque": {**episodes[2], "torque": episodes[2]["torque"][:, :1]},  # extra field width changes
            "action": {**episodes[2], "action": np.ones_like(episodes[2]["action"])},  # last row not 0
            "terminated": {**episodes[2], "terminated": np.ones_like(episodes[2]["terminated"])},
        }
        for name, episode in cases.items():
            with pytest.raises(DatasetError, match=f"field '{name}'"):
                writer.append_episode(episode)
        assert writer.num_episodes == 2
    ds = Dataset.load(out)
    assert ds.num_episodes == 2 and ds.info.complete
    np.testing.assert_array_equal(ds["state"], np.concatenate([episodes[0]["state"], episodes[1]["state"]]))
    with pytest.raises(DatasetError, match="file exists"):
        DatasetWriter(out, make_info())


def test_many_short_episodes_take_about_their_raw_size(tmp_path: Path) -> None:
    """Every episode is flushed (crash safety, SWMR). With compressed chunks each flush rewrote the half-filled last
    chunk elsewhere in the file and left the old copy as dead space: 900 reset windows of 51 rows took 148 MB where
    their data is 26 MB. Fixed-size chunks are rewritten in place."""
    rng = np.random.default_rng(1)
    episodes = [make_episode(rng, 20) for _ in range(200)]
    out = tmp_path / "short.h5"
    write_dataset(out, make_info(), episodes)
    raw = sum(v.nbytes for ep in episodes for v in ep.values())
    assert out.stat().st_size < 1.5 * raw
    assert Dataset.load(out).num_episodes == 200


def test_writer_killed_midway_keeps_finished_episodes(tmp_path: Path) -> None:
    out = tmp_path / "killed.h5"
    script = textwrap.dedent(f"""
        import sys, time
        import numpy as np
        sys.path[:0] = [{str(Path(__file__).parent)!r}, {str(Path(rwm_gym.__file__).parents[1])!r}]
        from test_dataset import make_episode, make_info
        from rwm_gym.data.dataset import DatasetWriter
        writer = DatasetWriter({str(out)!r}, make_info())
        rng = np.random.default_rng(0)
        for _ in range(3):
            writer.append_episode(make_episode(rng, 4, extra=True))
        print("wrote 3", flush=True)
        time.sleep(60)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "wrote 3"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    assert not out.exists()  # the destination only ever holds a whole file that plain h5py opens
    (partial,) = tmp_path.glob("killed.h5.partial-*")
    ds = Dataset.load(partial)
    assert ds.num_episodes == 3 and not ds.info.complete and ds.num_steps == 15
    np.testing.assert_array_equal(ds.episode(2)["state"], _third_state())


def test_a_second_process_writing_the_same_file_fails_at_once(tmp_path: Path, episodes) -> None:
    """Two `collect` runs on one file: the second stops before writing anything, the first finishes its file."""
    out = tmp_path / "shared.h5"
    second = (
        "import sys; from rwm_gym.data.dataset import DatasetWriter; from tests.test_dataset import make_info\n"
        "try:\n    DatasetWriter(sys.argv[1], make_info(), overwrite=True)\n"
        "except ValueError as err:\n    print(err); sys.exit(3)"
    )
    with DatasetWriter(out, make_info(), overwrite=True) as first:
        first.append_episode(episodes[0])
        run = subprocess.run(
            [sys.executable, "-c", second, str(out)], capture_output=True, text=True, cwd=Path(__file__).parent.parent
        )
        assert run.returncode == 3 and "being written by another run" in run.stdout, run.stderr
    with h5py.File(out, "r") as f:  # plain h5py, no SWMR flags
        assert bool(f.attrs["complete"]) and len(f["episode_lengths"]) == 1
    assert Dataset.load(out).num_episodes == 1 and not list(tmp_path.glob("*.partial-*"))
    assert not list(tmp_path.glob(".*.lock"))


def test_an_interrupted_writer_leaves_its_finished_episodes_at_the_destination(tmp_path: Path, episodes) -> None:
    out = tmp_path / "stopped.h5"
    with pytest.raises(KeyboardInterrupt):
        with DatasetWriter(out, make_info()) as writer:
            writer.append_episode(episodes[0])
            raise KeyboardInterrupt
    with h5py.File(out, "r") as f:
        assert not bool(f.attrs["complete"])
    assert Dataset.load(out).num_episodes == 1


def _third_state() -> np.ndarray:
    rng = np.random.default_rng(0)
    for _ in range(3):
        ep = make_episode(rng, 4, extra=True)
    return ep["state"]


def test_rows_beyond_sum_ignored_while_incomplete(path: Path, episodes) -> None:
    def append_orphan_rows(f):
        f.attrs["complete"] = False
        for name in f["steps"]:
            data = f["steps"][name]
            data.resize(len(data) + 3, axis=0)

    _edit(path, append_orphan_rows)
    ds = Dataset.load(path)
    assert not ds.info.complete and ds.num_episodes == 6
    assert len(ds["state"]) == ds.num_steps == sum(len(e["state"]) for e in episodes)
