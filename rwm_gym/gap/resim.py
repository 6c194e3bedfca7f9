"""Re-simulation of measured data: start a simulator at measured states, drive it with the measured actions.

A `Windows` holds many short stretches of measured episodes; `Resimulator.rollout` runs all of them at once on
`mujoco.batch` and returns the simulated states, so the residual simulated - measured can be taken per channel, step
and window. Each window first replays `warmup` measured steps (state overwritten with the measured one after each), so
state that is not in qpos/qvel, such as the actuator's delay buffer, holds the measured commands when the window starts.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from rwm_gym.data.dataset import Dataset
from rwm_gym.physics.params import PhysicsParams, build_model, dead_band
from rwm_gym.physics.robot import RobotLayout, measure
from rwm_gym.physics.simulator import BatchSimulator
from rwm_gym.spec import TaskSpec


@dataclass(frozen=True)
class Windows:
    """W measured windows of `horizon` transitions, each preceded by `warmup` replayed transitions."""

    episode: np.ndarray
    """(W,) episode index in the dataset."""
    start: np.ndarray
    """(W,) row (within the episode) where the re-simulation starts."""
    qpos: np.ndarray
    """(W, K+1, nq) measured qpos at rows start-K .. start."""
    qvel: np.ndarray
    """(W, K+1, nv) measured qvel at the same rows."""
    actions: np.ndarray
    """(W, K+H, A) measured actions at rows start-K .. start+H-1."""
    state0: np.ndarray
    """(W, S) measured state at row start."""
    target: np.ndarray
    """(W, H, S) measured state at rows start+1 .. start+H."""
    contact0: np.ndarray
    """(W, C) measured contact flags at row start."""
    horizon: int
    warmup: int

    def __len__(self) -> int:
        return len(self.start)

    def subset(self, mask: np.ndarray) -> Windows:
        """The windows where `mask` (W,) holds."""
        take = {k: getattr(self, k)[mask] for k in ("episode", "start", "qpos", "qvel", "actions", "state0",
                                                    "target", "contact0")}
        return Windows(**take, horizon=self.horizon, warmup=self.warmup)


def make_windows(dataset: Dataset, episodes: np.ndarray, horizon: int, stride: int, warmup: int = 2) -> Windows:
    """Every `stride`-th window of `horizon` transitions in the given episodes (none crosses an episode's end)."""
    parts: dict[str, list[np.ndarray]] = {k: [] for k in ("episode", "start", "qpos", "qvel", "actions", "state0",
                                                          "target", "contact0")}
    for e in np.asarray(episodes, int):
        ep = dataset.episode(int(e))
        rows = len(ep["state"])
        starts = np.arange(warmup, rows - horizon, stride)
        if len(starts) == 0:
            continue
        back = starts[:, None] + np.arange(-warmup, 1)[None]
        ahead = starts[:, None] + np.arange(1, horizon + 1)[None]
        acts = starts[:, None] + np.arange(-warmup, horizon)[None]
        parts["episode"].append(np.full(len(starts), e))
        parts["start"].append(starts)
        parts["qpos"].append(ep["qpos"][back])
        parts["qvel"].append(ep["qvel"][back])
        parts["actions"].append(ep["action"][acts].astype(np.float64))
        parts["state0"].append(ep["state"][starts])
        parts["target"].append(ep["state"][ahead])
        parts["contact0"].append(ep["contact"][starts])
    if not parts["start"]:
        raise ValueError(f"{dataset.path}: no episode is longer than {warmup + horizon} rows (needed for windows)")
    return Windows(**{k: np.concatenate(v) for k, v in parts.items()}, horizon=horizon, warmup=warmup)


class Resimulator:
    """Re-simulates windows of measured data on one robot model (the task spec's or `xml_file`)."""

    def __init__(self, spec: TaskSpec, xml_file: str | Path | None = None, nthread: int = 0):
        self.spec, self.xml_file, self.nthread = spec, xml_file, nthread

    def model(self, params: PhysicsParams) -> mujoco.MjModel:
        return build_model(self.spec, self.xml_file, params)

    def rollout(self, windows: Windows, params: PhysicsParams, horizon: int | None = None) -> np.ndarray:
        """Simulated states (W, H, S) at rows start+1 .. start+H of every window (H = horizon, default all)."""
        spec, horizon = self.spec, horizon or windows.horizon
        model = self.model(params)
        layout = RobotLayout.from_model(model, spec)
        keyframe = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, spec.keyframe)
        n, k = len(windows), windows.warmup
        sim = BatchSimulator(model, n, self.nthread, dead_band(spec, model, params))
        qpos, qvel = sim.batch.bind("qpos"), sim.batch.bind("qvel")
        ctrl = np.zeros((n, model.nu))
        act = spec.actuator
        default, scale = np.asarray(act.default_pose), act.action_scale

        def step(action: np.ndarray) -> None:
            ctrl[:, layout.actuator_ids] = default + scale * np.clip(action, -1.0, 1.0)
            sim.step(ctrl, spec.substeps)

        sim.reset(np.arange(n), keyframe, windows.qpos[:, 0], windows.qvel[:, 0])
        for i in range(k):
            if i > 0:
                qpos[:], qvel[:] = windows.qpos[:, i], windows.qvel[:, i]
                sim.batch.forward()
            step(windows.actions[:, i])
        if k > 0:
            qpos[:], qvel[:] = windows.qpos[:, k], windows.qvel[:, k]
            sim.batch.forward()
        out = np.empty((n, horizon, spec.state_dim))
        for h in range(horizon):
            step(windows.actions[:, k + h])
            out[:, h] = measure(layout, spec, **sim.arrays()).state
        return out


def normalised_residual(spec: TaskSpec, simulated: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """(simulated - measured) / the spec's state std, per channel; shapes (..., S)."""
    return (simulated - measured) / spec.state_std
