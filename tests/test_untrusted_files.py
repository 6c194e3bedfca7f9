"""Files a user can trust: crafted policy zips, datasets, checkpoints and specs run no code, read no file outside
themselves, never wait on a pipe and never inflate to gigabytes, through the public API and every command. Every
crafted file is made here (no binaries are committed); each refusal is one line naming the file and the entry or
field, exit status 2 from the CLI."""

from __future__ import annotations

import importlib.util
import os
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from synthetic_dynamics import write_linear_dataset

from rwm_gym.cli import main
from rwm_gym.resources import assets_dir

SHIPPED_POLICY = sorted((assets_dir() / "policies").glob("*.zip"))[0]
SECRET = b"secret-bytes-from-outside-the-file"


def one_line(capsys, *words: str) -> str:
    """The command's stderr (progress bars aside) is one line without a traceback, holding `words`."""
    lines = [ln for ln in capsys.readouterr().err.strip().splitlines() if ln.strip() and "%|" not in ln]
    err = "\n".join(lines)
    assert len(lines) == 1 and "Traceback" not in err, err
    for word in words:
        assert word in err, err
    return err


@pytest.fixture(scope="module")
def good_data(tmp_path_factory) -> Path:
    return write_linear_dataset(tmp_path_factory.mktemp("data") / "good.h5", num_episodes=4)


@pytest.fixture
def outside(tmp_path: Path) -> Path:
    """A file outside every input: what a crafted file would have rwm-gym read."""
    secret = tmp_path / "outside" / "secret.bin"
    secret.parent.mkdir()
    secret.write_bytes(SECRET * 64)
    return secret


# Datasets: HDF5 that reads other files or declares more than it holds -------------------------------------------


def _crafted(good: Path, out: Path, edit) -> Path:
    shutil.copy(good, out)
    with h5py.File(out, "a") as f:
        edit(f)
    return out


def _external_storage(secret: Path):
    def edit(f: h5py.File) -> None:
        rows = len(f["steps/reward"])
        f.create_dataset("steps/leak", shape=(rows,), dtype="u1", external=[(str(secret), 0, rows)])

    return edit


def _external_link(secret_h5: Path):
    def edit(f: h5py.File) -> None:
        f["steps/leak"] = h5py.ExternalLink(str(secret_h5), "/data")

    return edit


def _external_required_field(secret: Path):
    def edit(f: h5py.File) -> None:  # a required field itself kept in another file
        rows = len(f["steps/reward"])
        del f["steps/reward"]
        f.create_dataset("steps/reward", shape=(rows,), dtype="<f4", external=[(str(secret), 0, 4 * rows)])

    return edit


def _huge_unused_field(f: h5py.File) -> None:
    f.create_dataset("steps/unused", shape=(3 << 30,), dtype="u1", chunks=(1 << 20,))  # stores nothing


def _virtual(secret_h5: Path):
    def edit(f: h5py.File) -> None:
        layout = h5py.VirtualLayout(shape=(4,), dtype="f8")
        layout[:] = h5py.VirtualSource(str(secret_h5), "data", shape=(4,))
        f.create_virtual_dataset("steps/leak", layout)

    return edit


def _secret_h5(secret: Path) -> Path:
    out = secret.with_suffix(".h5")
    with h5py.File(out, "w") as f:
        f["data"] = np.frombuffer(SECRET[:32], dtype="f8")
    return out


BAD_DATASETS = {
    "external storage": (lambda s: _external_storage(s), ["field 'leak'", "another file"]),
    "external storage of a required field": (lambda s: _external_required_field(s), ["field 'reward'", "another"]),
    "external link": (lambda s: _external_link(_secret_h5(s)), ["field 'leak'", "links to"]),
    "virtual dataset": (lambda s: _virtual(_secret_h5(s)), ["field 'leak'", "virtual"]),
    "declared 3 GiB": (lambda s: _huge_unused_field, ["field 'unused'", "declares"]),
}


@pytest.mark.parametrize("case", BAD_DATASETS)
def test_a_dataset_that_reads_other_files_or_declares_gigabytes_is_refused_before_reading(
    tmp_path, good_data, outside, case
) -> None:
    from rwm_gym.data.dataset import Dataset, DatasetError

    make, words = BAD_DATASETS[case]
    bad = _crafted(good_data, tmp_path / "bad.h5", make(outside))
    with pytest.raises(DatasetError) as err:
        Dataset.load(bad)
    assert "\n" not in str(err.value) and str(bad) in str(err.value)
    for word in words:
        assert word in str(err.value)


@pytest.mark.parametrize("case", ["external storage", "external link", "declared 3 GiB"])
def test_train_and_export_refuse_such_a_dataset_in_one_line(tmp_path, good_data, outside, capsys, case) -> None:
    make, words = BAD_DATASETS[case]
    bad = _crafted(good_data, tmp_path / "bad.h5", make(outside))
    args = ["--iterations", "1", "--history", "4", "--forecast", "2", "--batch-size", "4", "--hidden-size", "8"]
    assert main(["train", "--data", str(bad), "--out", str(tmp_path / "m.safetensors"), *args, "--quiet"]) == 2
    one_line(capsys, str(bad), *words)
    assert not (tmp_path / "m.safetensors").exists()
    if importlib.util.find_spec("minari"):
        assert main(["export", "--minari", str(bad), "--out", str(tmp_path / "minari")]) == 2
        one_line(capsys, str(bad), *words)
        assert not (tmp_path / "minari").exists()


def test_a_dataset_path_that_is_a_fifo_is_refused_without_waiting(tmp_path) -> None:
    from rwm_gym.data.dataset import Dataset, DatasetError

    fifo = tmp_path / "data.h5"
    os.mkfifo(fifo)
    with pytest.raises(DatasetError, match="not a regular file"):
        Dataset.load(fifo)


def test_a_soft_link_inside_the_file_and_compressed_fields_still_load(tmp_path, good_data) -> None:
    from rwm_gym.data.dataset import Dataset

    def edit(f: h5py.File) -> None:
        f["alias"] = h5py.SoftLink("/steps/reward")
        f.create_dataset("steps/zeros", data=np.zeros(len(f["steps/reward"]), np.float32), compression="gzip")

    ds = Dataset.load(_crafted(good_data, tmp_path / "ok.h5", edit))
    assert "zeros" in ds.fields and not ds["zeros"].any()


@pytest.fixture(scope="module")
def good_minari(good_data, tmp_path_factory) -> Path:
    pytest.importorskip("minari")
    out = tmp_path_factory.mktemp("minari") / "m"
    assert main(["export", "--minari", str(good_data), "--out", str(out)]) == 0
    return out


def _minari_copy(good: Path, tmp_path: Path, edit) -> Path:
    folder = tmp_path / "m"
    shutil.copytree(good, folder)
    with h5py.File(folder / "main_data.hdf5", "a") as f:
        edit(f["episode_0"])
    return folder


@pytest.mark.parametrize("case", ["external storage", "external link", "declared 3 GiB"])
def test_import_refuses_a_minari_file_that_reads_other_files(tmp_path, good_minari, outside, capsys, case) -> None:
    def edit(group: h5py.Group) -> None:
        if case == "external storage":
            group.create_dataset("infos/leak", shape=(len(SECRET),), dtype="u1", external=[(str(outside), 0, 34)])
        elif case == "external link":
            group["infos/leak"] = h5py.ExternalLink(str(_secret_h5(outside)), "/data")
        else:
            group.create_dataset("infos/leak", shape=(3 << 30,), dtype="u1", chunks=(1 << 20,))

    folder = _minari_copy(good_minari, tmp_path, edit)
    assert main(["import", "--minari", str(folder), "--out", str(tmp_path / "back.h5")]) == 2
    one_line(capsys, "main_data.hdf5", "episode_0/infos/leak")
    assert not (tmp_path / "back.h5").exists()


def test_import_refuses_a_minari_file_that_links_out_of_its_folder(tmp_path, good_minari, capsys) -> None:
    folder = tmp_path / "m"
    shutil.copytree(good_minari, folder)
    elsewhere = tmp_path / "elsewhere.hdf5"
    (folder / "main_data.hdf5").rename(elsewhere)
    (folder / "main_data.hdf5").symlink_to(elsewhere)
    assert main(["import", "--minari", str(folder), "--out", str(tmp_path / "back.h5")]) == 2
    one_line(capsys, "main_data.hdf5", "link")
