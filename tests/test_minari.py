"""`rwm-gym export/import --minari`: a dataset survives the round trip through Minari field for field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rwm_gym.cli import main
from rwm_gym.data.collect import collect
from rwm_gym.data.dataset import Dataset

minari = pytest.importorskip("minari")


@pytest.mark.parametrize("env_id", ["DMC-Finger-Spin-v0", "AnymalD-MuJoCo-v0"])
def test_minari_round_trip_keeps_every_field(env_id: str, tmp_path: Path) -> None:
    data = collect(env_id, "random", 3, tmp_path / "data.h5", num_envs=2, max_steps=15, progress=False)
    assert main(["export", "--minari", str(data), "--out", str(tmp_path / "minari")]) == 0
    assert main(["import", "--minari", str(tmp_path / "minari"), "--out", str(tmp_path / "back.h5")]) == 0
    a, b = Dataset.load(data), Dataset.load(tmp_path / "back.h5")
    assert set(a.fields) == set(b.fields)
    for name in a.fields:
        assert a[name].dtype == b[name].dtype and np.array_equal(a[name], b[name]), name
    assert np.array_equal(a.episode_lengths, b.episode_lengths)
    assert a.info == b.info


def test_the_export_reads_as_a_plain_minari_dataset(tmp_path: Path) -> None:
    data = collect("DMC-Finger-Spin-v0", "random", 2, tmp_path / "data.h5", max_steps=10, progress=False)
    assert main(["export", "--minari", str(data), "--out", str(tmp_path / "m")]) == 0
    ds, source = minari.MinariDataset(tmp_path / "m"), Dataset.load(data)
    assert ds.total_episodes == 2 and ds.total_steps == 20
    episode = next(ds.iterate_episodes())
    assert episode.observations.shape == (11, source.spec().observation_dim)
    np.testing.assert_array_equal(episode.actions, source["action"][:10])
    np.testing.assert_array_equal(episode.rewards, source["reward"][:10])
    np.testing.assert_array_equal(episode.infos["state"], source["state"][:11])


def test_export_and_import_never_overwrite(tmp_path: Path, capsys) -> None:
    data = collect("DMC-Finger-Spin-v0", "random", 1, tmp_path / "data.h5", max_steps=5, progress=False)
    (tmp_path / "m").mkdir()
    assert main(["export", "--minari", str(data), "--out", str(tmp_path / "m")]) == 2
    assert main(["import", "--minari", str(tmp_path / "m"), "--out", str(data)]) == 2
    assert main(["import", "--minari", str(tmp_path / "nothing"), "--out", str(tmp_path / "x.h5")]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 3 and "exists" in errors[0] and "exists" in errors[1] and "Minari" in errors[2]
