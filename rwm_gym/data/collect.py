"""Collect episodes from a physics env into an HDF5 dataset (`rwm-gym collect`).

Runs N envs of a batched physics core side by side, in one process or in `--workers` workers (spawned processes or
Ray tasks, `rwm_gym.workers`); episode k always starts from seed `seed + k` (env and policy), so its content does not
depend on N, on the workers or on the backend. One writer appends
the episodes in episode order and flushes each at once: an interrupted collection keeps every episode written (those
that finished before an earlier one are held back until it is written). Where the physics blew up during a step
(`info["physics_diverged"]`: MuJoCo reset the simulation), the episode ends, truncated, at the last state before it,
as a robot's log that stops there: the reset is no motion of the robot.
"""

from __future__ import annotations

import functools
import glob
import inspect
import json
import os
import sys
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from rwm_gym.batched_core import check_num_envs
from rwm_gym.data.dataset import Dataset, DatasetError, DatasetInfo, DatasetWriter
from rwm_gym.output_guard import check_output, claim
from rwm_gym.policies.base import Policy
from rwm_gym.policies.factory import make_policy
from rwm_gym.registration import env_name, make_physics_core
from rwm_gym.spec import TaskSpec
from rwm_gym.workers import check_backend, run_in_workers, threads_per_worker, uses_workers

ROW_FIELDS = ("state", "contact", "foot_height", "terminated", "command", "qpos", "qvel")


def dataset_columns(core) -> dict[str, list[str]]:
    """Column names of every dataset field, from the task spec and the MuJoCo model."""
    spec = core.spec
    return {
        "state": list(spec.state_columns),
        "action": list(spec.actuator.joints),
        "contact": list(spec.privileged.contact_bodies),
        "foot_height": list(spec.privileged.feet),
        "command": list(spec.command.names),
        "qpos": _coordinate_names(core.model, velocity=False),
        "qvel": _coordinate_names(core.model, velocity=True),
    }


def _coordinate_names(model, velocity: bool) -> list[str]:
    import mujoco

    free = ["x", "y", "z", "wx", "wy", "wz"] if velocity else ["x", "y", "z", "qw", "qx", "qy", "qz"]
    ball = ["wx", "wy", "wz"] if velocity else ["qw", "qx", "qy", "qz"]
    names = []
    for j in range(model.njnt):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) or f"joint{j}"
        kind = model.jnt_type[j]
        suffixes = free if kind == mujoco.mjtJoint.mjJNT_FREE else ball if kind == mujoco.mjtJoint.mjJNT_BALL else [""]
        names += [f"{name}/{s}" if s else name for s in suffixes]
    return names


def collect(
    env_id: str | Path | TaskSpec,
    policy: str | Policy,
    episodes: int,
    out: str | Path,
    *,
    seed: int = 0,
    num_envs: int = 1,
    action_noise: float = 0.0,
    max_steps: int | None = None,
    env_kwargs: Mapping[str, object] | None = None,
    overwrite: bool = False,
    progress: bool = True,
    workers: int = 1,
    backend: str = "processes",
) -> Path:
    """Collect `episodes` episodes of `env_id` (a physics id, a spec path or a TaskSpec) driven by `policy` into `out`;
    returns the path.

    max_steps caps each episode's length (default: the spec's episode length). env_kwargs go to the physics core
    (e.g. `xml_file`, `physics`). workers > 1 (or backend "ray") runs that many workers of `backend` ("processes" or
    "ray", see `rwm_gym.workers`), each a batched core of `num_envs` envs, on blocks of episode numbers (`policy` must
    then be a name or a path); this process writes every episode in episode order, so the file is the same, byte for
    byte, whatever `workers`, `backend` and `num_envs` (tested for the random and gait policies; an SB3 policy acts on
    a batch, whose float rounding may depend on its size).
    """
    in_workers = uses_workers(workers, backend)
    _check_request(env_id, policy, episodes, out, max_steps, action_noise, env_kwargs, overwrite, workers, in_workers)
    check_backend(backend)
    job = _Job(
        env_id,
        policy,
        seed,
        min(check_num_envs(num_envs), episodes),
        action_noise,
        max_steps,
        dict(env_kwargs or {}),
        threads=threads_per_worker(workers, backend) if in_workers else 0,
    )
    runner = _Runner(job)
    spec, core, horizon = runner.core.spec, runner.core, runner.horizon
    info = DatasetInfo(
        env_id=env_name(env_id),
        spec_text=spec.text,
        dt=spec.policy_dt,
        columns=dataset_columns(core),
        policy=runner.policy.name,
        seed=seed,
        physics_params=core.params.to_dict(),
        metadata={"action_noise": action_noise, "max_steps": horizon, "env_kwargs": _jsonable(env_kwargs or {})},
    )
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with claim(out):
        resumed = _resume_point(out, info, episodes)
        first = 0 if resumed is None else resumed[1].num_episodes
        writer = None
        try:
            with (
                DatasetWriter(out, info, overwrite=overwrite) as writer,
                tqdm(total=episodes, desc=f"collect {spec.name}", unit="ep", disable=not progress) as bar,
            ):
                for k in range(first):  # the killed collection's episodes first
                    writer.append_episode(resumed[1].episode(k))
                    bar.update(1)
                if in_workers:
                    del runner, core  # the workers build their own
                    finished = _fan_out(job, range(first, episodes), workers, backend)
                else:
                    finished = runner.run(range(first, episodes))
                for episode in _in_order(finished, first):
                    writer.append_episode(episode)
                    bar.update(1)
        except BaseException:
            if resumed is not None and writer is not None and not writer.replaces and out.exists():
                resumed[0].unlink(missing_ok=True)  # its episodes are in `out` now (complete=false)
            raise
        if resumed is not None:  # only now: until `out` holds its episodes, the file keeps them
            resumed[0].unlink(missing_ok=True)
    return out


_RESUMABLE = ("partial", "resume")
"""Names of the files a killed collection of NAME leaves beside it: NAME.partial-XXXXXXXX (the writer's file) and
NAME.resume-XXXXXXXX (one being resumed from, while its episodes are copied)."""


def _resume_point(out: Path, info: DatasetInfo, episodes: int) -> tuple[Path, Dataset] | None:
    """The finished episodes a killed collection of `out` left (`_RESUMABLE`), when it collected the same episodes:
    the same task, policy, seed, physics and settings (episode k starts from seed + k, so they are this run's first
    episodes), at most `episodes` of them; the file is renamed out of the writer's way first, and None if there is
    none. The finished episodes of a killed collection with other settings are kept: moved to
    NAME.interrupted-XXXXXXXX.h5 beside `out`, said on stderr. Files holding no finished episode are left to the
    writer, which removes them. Call holding `claim(out)` (no other writer is running)."""
    found = []
    for kind in _RESUMABLE:
        for path in sorted(out.parent.glob(f"{glob.escape(out.name)}.{kind}-*")):
            try:
                data = Dataset.load(path)
            except (DatasetError, OSError):
                continue  # killed before its first episode: nothing to keep
            if data.num_episodes:
                found.append((path, data))
    same = [(p, d) for p, d in found if _same_collection(d.info, info) and d.num_episodes <= episodes]
    best = max(same, key=lambda pd: pd[1].num_episodes, default=None)
    for path, data in found:
        if best is not None and any(path == p for p, _ in same) and path != best[0]:
            path.unlink()  # the first episodes of the same collection, all in `best` too
        elif not any(path == p for p, _ in same):
            kept = out.with_name(f"{out.stem}.interrupted-{path.name.rsplit('-', 1)[-1]}{out.suffix}")
            os.replace(path, kept)
            print(
                f"{out}: a killed collection with other settings left {data.num_episodes} finished "
                f"episodes; kept in {kept}",
                file=sys.stderr,
            )
    if best is None:
        return None
    path, data = best
    moving = path.with_name(f"{out.name}.resume-{path.name.rsplit('-', 1)[-1]}")
    os.replace(path, moving)
    print(f"{out}: resuming from the {data.num_episodes} finished episodes of a killed collection", file=sys.stderr)
    return moving, data


def _same_collection(found: DatasetInfo, info: DatasetInfo) -> bool:
    """Whether a killed collection's file holds the first episodes of the collection `info` describes."""
    fields = ("env_id", "spec_text", "dt", "columns", "policy", "seed", "physics_params", "metadata")
    return all(json.dumps(getattr(found, f)) == json.dumps(getattr(info, f)) for f in fields)


def _check_request(
    env_id, policy, episodes, out, max_steps, action_noise, env_kwargs, overwrite, workers, in_workers
) -> None:
    """`collect`'s arguments checked before anything runs: counts, noise, the output (not an input, not another
    run's) and what the workers can carry; a ValueError or DatasetError of one line otherwise."""
    if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)) or episodes < 1:
        raise ValueError(f"episodes must be a positive integer, got {episodes!r}")
    if max_steps is not None and max_steps < 1:
        raise ValueError(f"max_steps must be a positive number of policy steps, got {max_steps}")
    if not (np.isfinite(action_noise) and action_noise >= 0):
        raise ValueError(f"action_noise must be a finite std >= 0, got {action_noise!r}")
    if Path(out).exists() and not overwrite:
        raise DatasetError(f"{out}: file exists (pass --overwrite, or overwrite=True, to replace it)")
    inputs = [
        policy if isinstance(policy, str) and policy.endswith(".zip") else None,
        env_id if isinstance(env_id, (str, Path)) and Path(env_id).suffix == ".toml" else None,
        *(str(v) for k, v in (env_kwargs or {}).items() if k == "xml_file"),
    ]
    check_output(out, inputs=inputs, overwrite=overwrite)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if in_workers and not isinstance(policy, str):
        raise ValueError("collect in workers needs the policy as a name or a path, not an object")


def finished_collection(path: str | Path, *, episodes: int, seed: int, what: str = "this collection") -> bool:
    """Whether `path` already holds `episodes` complete episodes collected from `seed`: a script that collects fixed
    parts keeps those from before an interruption and collects again one cut short. A file from another seed is not
    the script's to replace: DatasetError naming `what` it should have been."""
    path = Path(path)
    if not path.exists():
        return False
    found = Dataset.load(path)
    if found.info.seed != seed:
        raise DatasetError(f"{path} exists and is not {what} (seed {found.info.seed}, not {seed})")
    return found.info.complete and found.num_episodes == episodes


@dataclass(frozen=True)
class _Job:
    """What a collection process needs to turn episode numbers into episodes (picklable, for workers)."""

    env_id: str
    policy: str | Policy
    seed: int
    num_envs: int
    action_noise: float
    max_steps: int | None
    env_kwargs: dict
    threads: int = 0
    """mujoco.batch threads of the core (0: all CPUs), where the core takes the option."""


class _Runner:
    """One batched physics core and its policy; episode k always starts from seed `seed + k`."""

    def __init__(self, job: _Job) -> None:
        kwargs = dict(job.env_kwargs)
        if job.threads and _takes_nthread(job.env_id):
            kwargs["nthread"] = job.threads
        self.job, self.core = job, make_physics_core(job.env_id, job.num_envs, **kwargs)
        spec = self.core.spec
        self.policy = (
            make_policy(job.policy, spec, job.num_envs, action_noise=job.action_noise)
            if isinstance(job.policy, str)
            else job.policy
        )
        self.horizon = min(job.max_steps or spec.episode_steps, spec.episode_steps)

    def run(self, numbers: range) -> Iterator[tuple[int, dict[str, np.ndarray]]]:
        """(k, episode) for every episode number k in `numbers`, in the order they finish."""
        core, pol, seed, num_envs, spec = self.core, self.policy, self.job.seed, self.job.num_envs, self.core.spec
        buffers: list[list[dict] | None] = [None] * num_envs
        episode_of = np.zeros(num_envs, dtype=np.int64)
        todo = iter(numbers)

        def start(ids: np.ndarray) -> np.ndarray:
            ks = [k for _, k in zip(ids, todo)]
            ids = ids[: len(ks)]
            if len(ids) == 0:
                return ids
            core.reset(ids, [seed + k for k in ks])
            pol.reset(ids, [np.random.default_rng([seed + k, 1]) for k in ks])
            episode_of[ids] = ks
            record = core.record()
            for i in ids:
                buffers[i] = [{f: record[f][i] for f in ROW_FIELDS}]
            return ids

        obs = np.zeros((num_envs, spec.observation_dim), dtype=np.float32)
        ids = start(np.arange(num_envs))
        obs[ids] = core.observe(ids)
        while any(b is not None for b in buffers):
            actions = pol.act(obs)
            obs, reward, terminated, truncated, info = core.step(actions)
            record = core.record()
            truncated = truncated | (core.steps >= self.horizon) & ~terminated
            diverged = info.get("physics_diverged", np.zeros(num_envs, dtype=bool))
            finished = []
            for i in range(num_envs):
                rows = buffers[i]
                if rows is None:
                    continue
                if diverged[i]:  # the step's state is MuJoCo's reset, no motion: the log stops before it
                    rows[-1]["truncated"] = True
                    yield int(episode_of[i]), stack_episode(rows, spec.action_dim)
                    buffers[i] = None
                    finished.append(i)
                    continue
                rows[-1]["action"], rows[-1]["reward"] = actions[i], reward[i]
                rows.append({f: record[f][i] for f in ROW_FIELDS})
                if terminated[i] or truncated[i]:
                    rows[-1]["truncated"] = bool(truncated[i])
                    yield int(episode_of[i]), stack_episode(rows, spec.action_dim)
                    buffers[i] = None
                    finished.append(i)
            if finished:
                restarted = start(np.asarray(finished))
                if len(restarted):
                    obs[restarted] = core.observe(restarted)


def _takes_nthread(env_id: str | Path | TaskSpec) -> bool:
    """Whether the core's entry point takes `nthread`: by name, or among its keyword arguments (`make_core`'s
    `PhysicsOptions` fields)."""
    from rwm_gym.registration import _entry, resolve_spec

    parameters = inspect.signature(_entry(resolve_spec(env_id), "core_entry_point")).parameters
    return "nthread" in parameters or any(p.kind is p.VAR_KEYWORD for p in parameters.values())


def _in_order(finished: Iterable[tuple[int, dict]], first: int = 0) -> Iterator[dict]:
    """Episodes in episode-number order (first, first + 1, ...), holding back those that finish before an earlier
    one."""
    waiting, next_k = {}, first
    for k, episode in finished:
        waiting[k] = episode
        while next_k in waiting:
            yield waiting.pop(next_k)
            next_k += 1


_WORKER: _Runner | None = None


def _worker_block(job: _Job, numbers: range) -> list[tuple[int, dict]]:
    """A worker's share: the episodes of one block of numbers (the core is built once per process)."""
    global _WORKER
    if _WORKER is None or _WORKER.job != job:
        _WORKER = _Runner(job)
    return list(_WORKER.run(numbers))


def _fan_out(job: _Job, numbers: range, workers: int, backend: str) -> Iterator[tuple[int, dict]]:
    """The episodes `numbers` from `workers` workers of `backend`; blocks of numbers go to whichever worker is free
    and come back in order."""
    block = max(1, min(4 * job.num_envs, -(-len(numbers) // workers)))  # a few waves of envs, all workers busy
    blocks = [range(a, min(a + block, numbers.stop)) for a in range(numbers.start, numbers.stop, block)]
    for result in run_in_workers(functools.partial(_worker_block, job), blocks, workers, backend):
        yield from result


def diverged_episodes(data: Dataset) -> np.ndarray:
    """Indices of the episodes of a collection that ended where the physics blew up: truncated before the
    collection's `max_steps` transitions (the collector truncates there and at that cap only)."""
    cap = data.info.metadata.get("max_steps")
    if cap is None:
        return np.zeros(0, dtype=np.int64)
    last = data.episode_starts + data.episode_lengths - 1
    return np.flatnonzero(data["truncated"][last] & (data.episode_lengths - 1 < cap))


def stack_episode(rows: list[dict], action_dim: int) -> dict[str, np.ndarray]:
    """Stack buffered rows into dataset arrays; the last row carries no transition."""
    rows[-1]["action"], rows[-1]["reward"] = np.zeros(action_dim), 0.0
    n = len(rows)
    episode = {f: np.stack([r[f] for r in rows]) for f in ROW_FIELDS if f != "terminated"}
    episode["action"] = np.stack([r["action"] for r in rows]).astype(np.float32)
    episode["reward"] = np.asarray([r["reward"] for r in rows], dtype=np.float32)
    episode["terminated"] = np.zeros(n, dtype=bool)
    episode["truncated"] = np.zeros(n, dtype=bool)
    episode["terminated"][-1] = bool(rows[-1]["terminated"])
    episode["truncated"][-1] = rows[-1].get("truncated", False) and not episode["terminated"][-1]
    return episode


def _jsonable(value):
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in value]
    if hasattr(value, "to_dict"):
        return value.to_dict()
    return value if isinstance(value, (int, float, str, bool, type(None))) else str(value)
