"""Physics rows through a model's lineage: a fine-tune adds only the data its start model had not seen, a merge holds
its parts' sources, a reset cut adds none, `rwm-gym ppo` prints the total with its share of N_mf, and the shipped
models carry their documented lineage."""

from __future__ import annotations

from pathlib import Path

import pytest
from synthetic_dynamics import SPEC, write_linear_dataset

from rwm_gym.data.dataset import Dataset, merge_datasets
from rwm_gym.data.lineage import SOURCES_KEY, physics_sources
from rwm_gym.imagination.reset_data import make_reset_data
from rwm_gym.model import model_config_for
from rwm_gym.model.checkpoint import load_checkpoint, read_meta, save_checkpoint
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.lineage import n_mf, physics_rows, share_text
from rwm_gym.model.train import train
from rwm_gym.resources import assets_dir

TINY = TrainConfig(history=4, forecast=2, batch_size=4, iterations=2, val_every=2, val_fraction=0.25)


def _train(data: Path, out: Path, init: Path | None = None) -> Path:
    config = model_config_for("mlp", SPEC, hidden_size=8, head_hidden=8)
    return train(data, config, TINY, out, progress=False, init=init).path


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("lineage")
    return {name: write_linear_dataset(folder / f"{name}.h5", seed=seed) for name, seed in (("a", 0), ("b", 1))}


def _rows(path: Path) -> int:
    return int(Dataset.load(path).num_steps)


def test_a_merge_holds_each_part_once_and_a_reset_cut_adds_none(files, tmp_path):
    a, b = files["a"], files["b"]
    ab = tmp_path / "ab.h5"
    merge_datasets([a, b], ab)
    assert sum(physics_sources(Dataset.load(ab)).values()) == _rows(a) + _rows(b)
    again = tmp_path / "ab_a.h5"
    merge_datasets([ab, a], again)  # a buffer that holds an earlier buffer and one of its parts
    assert physics_sources(Dataset.load(again)) == physics_sources(Dataset.load(ab))
    cut = make_reset_data(ab, tmp_path / "reset.h5", episodes=3, rows=20)
    assert Dataset.load(cut).num_steps < _rows(ab)
    assert physics_sources(Dataset.load(cut)) == physics_sources(Dataset.load(ab))


def test_a_fine_tune_carries_its_start_models_rows_and_adds_only_new_data(files, tmp_path):
    a, b = files["a"], files["b"]
    first = _train(a, tmp_path / "first.safetensors")
    assert physics_rows(first)[0] == _rows(a)
    only_b = _train(b, tmp_path / "b.safetensors", init=first)  # fine-tuned on other data: both
    assert physics_rows(only_b)[0] == _rows(a) + _rows(b)
    buffer = tmp_path / "buffer.h5"
    merge_datasets([a, b], buffer)
    on_buffer = _train(buffer, tmp_path / "buffer.safetensors", init=first)  # a is in the buffer and the start model
    assert physics_rows(on_buffer)[0] == _rows(a) + _rows(b)
    twice = _train(buffer, tmp_path / "twice.safetensors", init=on_buffer)  # the same data again: nothing new
    assert physics_rows(twice)[0] == _rows(a) + _rows(b)
    assert read_meta(twice).provenance["physics_rows"] == _rows(a) + _rows(b)
    scratch = _train(buffer, tmp_path / "scratch.safetensors")  # from scratch: its data alone
    assert physics_rows(scratch)[0] == _rows(a) + _rows(b)


def test_rwm_gym_train_init_fine_tunes_with_the_start_models_rows(files, tmp_path):
    from rwm_gym.cli import main

    tiny = ["--iterations", "2", "--history", "4", "--forecast", "2", "--batch-size", "4", "--val-fraction", "0.25"]
    first, second = tmp_path / "first.safetensors", tmp_path / "second.safetensors"
    model = ["--model", "mlp", "--hidden-size", "8", "--head-hidden", "8"]
    assert main(["train", "--data", str(files["a"]), "--out", str(first), *model, *tiny, "--quiet"]) == 0
    assert main(["train", "--data", str(files["b"]), "--init", str(first), "--out", str(second), *tiny, "--quiet"]) == 0
    assert physics_rows(second)[0] == _rows(files["a"]) + _rows(files["b"])


def test_a_checkpoint_from_before_lineages_counts_its_dataset_and_says_so(files, tmp_path):
    model, meta = load_checkpoint(_train(files["a"], tmp_path / "m.safetensors"))
    older = tmp_path / "older.safetensors"
    provenance = {k: v for k, v in meta.provenance.items() if k not in (SOURCES_KEY, "physics_rows")}
    save_checkpoint(older, model, meta.spec, provenance=provenance)
    rows, why = physics_rows(older)
    assert rows == _rows(files["a"]) and "not counted" in why
    bad = tmp_path / "bad.safetensors"
    save_checkpoint(bad, model, meta.spec, provenance={**meta.provenance, SOURCES_KEY: {"x": -1}})
    with pytest.raises(ValueError, match="row counts"):
        physics_rows(bad)


def test_share_of_n_mf_is_worded_against_the_teachers_steps():
    assert n_mf() == 32_243_712
    assert share_text(3_224_371).startswith("3,224,371 (10.0 % of N_mf = 32.2 M")
    assert share_text(None) == "?"


def test_n_mf_is_the_tasks_own_teachers():
    assert n_mf("Go2-MuJoCo-v0") == 53_084_160  # the Go2 teacher's record, not ANYmal D's
    assert share_text(5_308_416, "Go2-MuJoCo-v0").startswith("5,308,416 (10.0 % of N_mf = 53.1 M")
    assert n_mf("G1Legs-MuJoCo-v0") is None  # its teacher never reached 0.80: the rows alone, no share
    assert share_text(1_000, "G1Legs-MuJoCo-v0") == (
        "1,000 (no N_mf: no shipped model-free teacher of G1Legs-MuJoCo-v0 reached tracking 0.80)"
    )


def test_the_shipped_models_carry_their_documented_lineage():
    folder = assets_dir() / "checkpoints"
    documented = {  # docs/concepts/world-model.md: each model's data plus every model it was fine-tuned from
        "anymal_d_rwm_mbpo": 1_553_211,
        "anymal_d_rwm_cover": 1_852_377,
        "anymal_d_rwm_cover_history": 2_275_759,
        "anymal_d_rwm_taught": 2_496_757,  # its buffer holds cover_history's: counted once
    }
    for name, rows in documented.items():
        assert physics_rows(folder / f"{name}.safetensors")[0] == rows, name
