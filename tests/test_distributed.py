"""Data-parallel training (torchrun, gloo, 2 CPU processes): a global batch split over 2 ranks follows the
single-process loss curve, writes the same checkpoint format, and resumes whatever the world size.

The comparison runs without forecast noise (teacher forcing and the Gaussian NLL), where both runs see the same
windows and compute the same mean gradient; with sampled feedback each rank draws its own noise (documented)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors import safe_open
from synthetic_dynamics import write_linear_dataset

from rwm_gym.cli import main
from rwm_gym.model import distributed
from rwm_gym.model.checkpoint import read_meta

TESTS = Path(__file__).parent
RUN = [
    "--teacher-forcing",
    "--loss",
    "nll",
    "--schedule",
    "constant",
    "--history",
    "6",
    "--batch-size",
    "8",
    "--val-every",
    "1",
    "--checkpoint-every",
    "3",
    "--val-fraction",
    "0.25",
    "--hidden-size",
    "16",
    "--num-layers",
    "1",
    "--head-hidden",
    "16",
    "--ensemble-size",
    "2",
    "--quiet",
]


def torchrun(*args: str, nproc: int = 2) -> subprocess.CompletedProcess:
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "PYTHONPATH": os.pathsep.join(filter(None, [str(TESTS.parent), str(TESTS), os.environ.get("PYTHONPATH")])),
    }
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}", *args]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def train_cli(
    data: Path, out: Path, iterations: int, *, ranks: int, resume: bool = False, extra: list[str] | None = None
) -> None:
    args = ["train", "--data", str(data), "--out", str(out), "--iterations", str(iterations), *RUN, *(extra or [])]
    args += ["--resume"] if resume else []
    if ranks == 1:
        assert main(args) == 0  # one torch thread: conftest's autouse fixture
    else:
        torchrun("-m", "rwm_gym.cli", *args, nproc=ranks)


def tensors(path: Path) -> dict[str, torch.Tensor]:
    with safe_open(str(path), framework="pt") as f:
        return {name: f.get_tensor(name) for name in f.keys()}


def assert_same_weights(a: Path, b: Path, rtol: float = 1e-4, atol: float = 1e-5) -> None:
    ta, tb = tensors(a), tensors(b)
    model = [k for k in ta if k.startswith("model/")]
    assert model and set(model) == {k for k in tb if k.startswith("model/")}
    assert set(ta) <= set(tb) or set(tb) <= set(ta)  # a cuda run also keeps its cuda RNG state (train/rng_cuda)
    for name in model:
        torch.testing.assert_close(ta[name], tb[name], rtol=rtol, atol=atol, msg=lambda m, name=name: f"{name}: {m}")


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return write_linear_dataset(tmp_path_factory.mktemp("data") / "linear.h5")


@pytest.fixture(scope="module")
def single(data: Path, tmp_path_factory) -> Path:
    """The reference: one process, the whole batch, 6 iterations."""
    out = tmp_path_factory.mktemp("single") / "m.safetensors"
    train_cli(data, out, 6, ranks=1)
    return out


def test_two_ranks_follow_the_single_process_loss_curve_in_the_same_format(
    data: Path, single: Path, tmp_path: Path
) -> None:
    out = tmp_path / "ddp.safetensors"
    train_cli(data, out, 6, ranks=2)
    one, two = read_meta(single), read_meta(out)
    curve_one = [(e["iteration"], e["train_loss"], e["val_error"]) for e in one.stats["log"]]
    curve_two = [(e["iteration"], e["train_loss"], e["val_error"]) for e in two.stats["log"]]
    assert [c[0] for c in curve_two] == [1, 2, 3, 4, 5, 6]
    for (i, loss1, val1), (_, loss2, val2) in zip(curve_one, curve_two, strict=True):
        assert loss2 == pytest.approx(loss1, rel=1e-5), i
        assert val2 == pytest.approx(val1, rel=1e-5), i
    assert curve_one[-1][1] < curve_one[0][1]  # it did learn: the curve is not flat
    assert two.train_config == one.train_config and two.model_config == one.model_config
    assert set(two.provenance) == set(one.provenance) and set(two.stats) == set(one.stats)
    assert_same_weights(single, out)
    ta, tb = tensors(single), tensors(out)
    assert {k: (v.shape, v.dtype) for k, v in ta.items()} == {k: (v.shape, v.dtype) for k, v in tb.items()}


def test_resume_continues_whatever_the_world_size(data: Path, single: Path, tmp_path: Path) -> None:
    two_then_one = tmp_path / "a.safetensors"
    train_cli(data, two_then_one, 3, ranks=2)
    train_cli(data, two_then_one, 6, ranks=1, resume=True)
    one_then_two = tmp_path / "b.safetensors"
    train_cli(data, one_then_two, 3, ranks=1)
    train_cli(data, one_then_two, 6, ranks=2, resume=True)
    for path in (two_then_one, one_then_two):
        assert read_meta(path).stats["iterations"] == 6
        assert_same_weights(single, path)


def test_every_model_kind_keeps_its_ranks_in_sync_with_forecast_noise(data: Path) -> None:
    done = torchrun(str(TESTS / "ddp_every_kind.py"), str(data))
    lines = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    by_rank = {rank: {(r["kind"], r["ensemble"]): r for r in lines if r["rank"] == rank} for rank in (0, 1)}
    assert len(by_rank[0]) == 10 and by_rank[0].keys() == by_rank[1].keys()  # 9 kinds x heads + a timed run
    for key, result in by_rank[0].items():
        assert by_rank[1][key]["weights"] == result["weights"], key  # identical parameters on both ranks
        assert by_rank[1][key]["train_loss"] == result["train_loss"], key  # the logged loss is the global mean
        assert by_rank[1][key].get("iterations") == result.get("iterations"), key  # a time budget ends together


def test_a_batch_that_does_not_split_over_the_ranks_is_refused() -> None:
    world = distributed.World(rank=1, size=3)
    with pytest.raises(ValueError, match="multiple of 3"):
        distributed.check_batch(8, world)
    batch = torch.arange(9)
    assert distributed.shard(batch, world).tolist() == [3, 4, 5]
    assert distributed.shard(batch, distributed.SINGLE) is batch
    assert len({distributed.rank_seed(0, r, 100) for r in range(1, 5)}) == 4
