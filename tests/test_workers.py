"""Work over workers (`rwm_gym.workers`): results in the order of the items on either backend, and `rwm-gym collect`
and `rwm-gym score` on a local Ray cluster of 2 CPUs give one process's bytes and figures, on tiny budgets."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import pytest

from rwm_gym.cli import main
from rwm_gym.data.dataset import Dataset
from rwm_gym.workers import RayMissing, check_backend, run_in_workers

TESTS = Path(__file__).parent


@pytest.fixture(scope="module")
def ray_cluster():
    """A new local Ray cluster of 2 CPUs for this file's tests (started in about 5 s), whatever cluster `ray start`
    left on this machine; its workers import this checkout's rwm_gym and this folder's modules."""
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install 'rwm-gym[ray]')")
    path = os.pathsep.join(filter(None, [str(TESTS.parent), str(TESTS), os.environ.get("PYTHONPATH")]))
    ray.init(
        address="local",
        num_cpus=2,
        include_dashboard=False,
        log_to_driver=False,
        runtime_env={"env_vars": {"PYTHONPATH": path, "OMP_NUM_THREADS": "1"}},
    )
    try:
        yield ray
    finally:
        ray.shutdown()


def slow_square(x: int) -> int:
    """The first items finish last."""
    time.sleep(0.2 * (3 - x))
    if x < 0:
        raise ValueError(f"negative item {x}")
    return x * x


@pytest.mark.parametrize("backend", ["processes", "ray"])
def test_results_come_back_in_the_order_of_the_items(request, backend):
    if backend == "ray":
        request.getfixturevalue("ray_cluster")
    assert list(run_in_workers(slow_square, range(4), 2, backend)) == [0, 1, 4, 9]
    with pytest.raises(ValueError, match="negative item"):
        list(run_in_workers(slow_square, [1, -1, 2], 2, backend))


def test_a_missing_ray_is_one_line(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now raises ImportError
    with pytest.raises(RayMissing, match=r"pip install 'rwm-gym\[ray\]'"):
        check_backend("ray")
    with pytest.raises(ValueError, match="backend must be one of"):
        check_backend("dask")
    out = tmp_path / "d.h5"
    assert main(["collect", "--out", str(out), "--episodes", "1", "--backend", "ray"]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "--backend ray needs the ray package" in error and not out.exists()
    with pytest.raises(SystemExit, match="needs the ray package"):
        main(["score", "--policy", "zero", "--out", str(tmp_path / "s"), "--backend", "ray"])


def test_ray_collection_writes_the_bytes_of_one_process(ray_cluster, tmp_path):
    """Random actions make episodes of different lengths, which finish out of order in each task."""
    common = ["collect", "--policy", "random", "--episodes", "7", "--num-envs", "2", "--max-steps", "100"]
    assert main([*common, "--out", str(tmp_path / "one.h5")]) == 0
    assert main([*common, "--out", str(tmp_path / "ray.h5"), "--backend", "ray", "--workers", "2"]) == 0
    assert len(set(Dataset.load(tmp_path / "one.h5").episode_lengths)) > 1
    assert (tmp_path / "one.h5").read_bytes() == (tmp_path / "ray.h5").read_bytes()


def test_ray_score_gives_the_figures_of_one_process(ray_cluster, tmp_path):
    reports = []
    for extra in ([], ["--backend", "ray", "--workers", "2"]):
        out = tmp_path / ("ray" if extra else "one")
        command = ["score", "--policy", "gait", "--out", str(out), "--seeds", "2", "--steps", "6", "--commands", "1"]
        assert main([*command, *extra]) == 0
        report = json.loads((out / "score.json").read_text())
        for evaluation in (report["evaluation"], report["floor_evaluation"]):
            evaluation.pop("wall_s")
        reports.append(report)
    assert reports[0]["episodes"] == 6 and reports[0] == reports[1]
