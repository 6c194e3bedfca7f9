"""Work spread over workers: spawned processes on this machine, or Ray tasks on a Ray cluster of many machines.

`run_in_workers(fn, items, workers, backend)` calls `fn(item)` for every item, at most `workers` at a time, and yields
the results in the order of `items`, each as soon as it and every one before it are done. Callers cut their work into
items whose results do not depend on where they ran (`rwm-gym collect`: blocks of episode numbers, each episode seeded
by its number; `rwm-gym score`: consecutive blocks of (command, seed) episodes), so the same seeds give the same
results with any number of workers and either backend.

- "processes" (the default): a pool of `workers` processes started with spawn (fresh interpreters, no forked MuJoCo or
  torch threads); `fn` and the items are pickled.
- "ray": Ray tasks of one CPU each, on the cluster `ray.init()` finds: the one `ray start` made on this machine, or
  the one RAY_ADDRESS names, else a new local one. `fn` and the items travel by cloudpickle; every node needs the
  same rwm-gym installed. Ray is imported here only, and only when this backend is picked (`pip install
  'rwm-gym[ray]'`).

Both backends reuse a worker process for several items, so a module global of `fn`'s module (a physics core built
once) lives on between them.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

BACKENDS = ("processes", "ray")
"""Where `run_in_workers` runs its items: spawned processes on this machine, or Ray tasks."""

RAY_INSTALL = "pip install 'rwm-gym[ray]'"
"""What installs the package the ray backend needs."""

Item = TypeVar("Item")
Result = TypeVar("Result")


class RayMissing(ImportError):
    """The ray backend was picked and the ray package is not installed (its message is one line naming the extra)."""


def check_backend(backend: str) -> None:
    """A one-line ValueError for an unknown backend; `RayMissing` for "ray" without the package."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if backend == "ray":
        try:
            import ray  # noqa: F401
        except ImportError:
            raise RayMissing(f"--backend ray needs the ray package: {RAY_INSTALL}") from None


def uses_workers(workers: int, backend: str) -> bool:
    """Whether work goes to workers: more than one, or any Ray task (one Ray task may run on another machine); one
    worker of the processes backend is this process itself."""
    return workers > 1 or backend != "processes"


def threads_per_worker(workers: int, backend: str = "processes") -> int:
    """MuJoCo/torch threads of each worker: this machine's cores shared among the processes; one for a Ray task
    (Ray schedules tasks by CPU, one each)."""
    return max(1, (os.cpu_count() or 1) // workers) if backend == "processes" else 1


def run_in_workers(
    fn: Callable[[Item], Result], items: Iterable[Item], workers: int, backend: str = "processes"
) -> Iterator[Result]:
    """`fn(item)` for every item on `workers` workers of `backend`; the results in the order of `items`.

    `fn` must be picklable (a module-level function, or a `functools.partial` of one). A worker's exception is
    raised here, and the remaining work is dropped.
    """
    check_backend(backend)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    items = list(items)
    if backend == "ray":
        yield from _ray(fn, items, workers)
        return
    import multiprocessing

    with multiprocessing.get_context("spawn").Pool(min(workers, len(items)) or 1) as pool:
        yield from pool.imap(fn, items)


def _ray(fn: Callable[[Item], Result], items: list[Item], workers: int) -> Iterator[Result]:
    """Ray tasks of `fn`, a new one started whenever one of the `workers` running finishes (as a pool would); the
    results handed out in the order the items were submitted."""
    import ray

    if not ray.is_initialized():
        ray.init(include_dashboard=False)
    task, shared_fn = ray.remote(num_cpus=1)(_call), ray.put(fn)  # fn (a job's settings) sent once
    submitted, running, todo, handed_out = [], set(), iter(items), 0
    try:
        while True:
            for item in todo:
                submitted.append(task.remote(shared_fn, item))
                running.add(submitted[-1])
                if len(running) == workers:
                    break
            while handed_out < len(submitted) and submitted[handed_out] not in running:
                yield ray.get(submitted[handed_out])
                submitted[handed_out] = None  # its result may leave the object store
                handed_out += 1
            if not running:
                return
            done, _ = ray.wait(list(running), num_returns=1)
            running.difference_update(done)
    finally:
        for ref in running:
            ray.cancel(ref)


def _call(fn: Callable[[Item], Result], item: Item) -> Result:
    """A Ray task: `fn(item)` (Ray's remote functions are plain functions, not partials)."""
    return fn(item)
