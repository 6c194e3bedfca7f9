"""Two interchangeable ways to step N copies of one MuJoCo model: one `MjData` (N = 1) or `mujoco.batch.Batch`.

Both expose the same arrays with a leading batch axis, and both leave every derived quantity computed at the new
state after a step (`mj_forward`), so the single env and the batched env see bit-identical transitions. With drive
rewrites (`DeadBand`, gear backlash; `TorqueSpeedLimit`, a drive's torque-speed curve) both step one physics step at a
time and rewrite the controls before each, in the order given.

Where MuJoCo's integration blows up (a huge or non-finite acceleration, velocity or position), MuJoCo warns, resets
that simulation to the model's default pose and goes on, which looks like a robot teleported. Both simulators mark
such a step in `diverged`, so that the task can end the episode instead of carrying on from the reset.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import mujoco
import numpy as np
from mujoco import batch as mjbatch

DIVERGENCE_WARNINGS: dict[int, str] = {
    int(mujoco.mjtWarning.mjWARN_BADQACC): "Nan, Inf or huge value in QACC",
    int(mujoco.mjtWarning.mjWARN_BADQVEL): "Nan, Inf or huge value in QVEL",
    int(mujoco.mjtWarning.mjWARN_BADQPOS): "Nan, Inf or huge value in QPOS",
    int(mujoco.mjtWarning.mjWARN_BADCTRL): "Nan, Inf or huge value in CTRL",
}
"""MuJoCo warnings that mean the simulation blew up (and was reset by MuJoCo)."""
_DIVERGENCE_CODES = list(DIVERGENCE_WARNINGS)


class DriveRewrite(Protocol):
    """Something a drive does that MuJoCo's actuators cannot hold, applied by rewriting the controls before every
    physics step (`DeadBand`, `TorqueSpeedLimit`)."""

    def control(self, ctrl: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        """Rewritten controls (N, nu) for controls (N, nu) at qpos (N, nq) and qvel (N, nv)."""


class SingleSimulator:
    """One simulation on an `MjData`."""

    num_envs = 1

    def __init__(self, model: mujoco.MjModel, drives: Sequence[DriveRewrite] = ()):
        self.model = model
        self.data = mujoco.MjData(model)
        self.drives = tuple(drives)
        self.diverged = np.zeros(1, dtype=bool)
        """(1,) whether the simulation blew up (and MuJoCo reset it) during the last `step`."""

    def reset(self, ids: np.ndarray, keyframe: int, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Reset to `keyframe`, then set qpos (n, nq) and qvel (n, nv) of the simulations `ids` (here: [0])."""
        mujoco.mj_resetDataKeyframe(self.model, self.data, keyframe)
        self.data.qpos[:] = qpos[0]
        self.data.qvel[:] = qvel[0]
        mujoco.mj_forward(self.model, self.data)

    def step(self, ctrl: np.ndarray, nstep: int) -> None:
        """Hold ctrl (1, nu) for nstep physics steps (with drive rewrites: rewritten before each)."""
        before = self._divergences()
        if not self.drives:
            self.data.ctrl[:] = ctrl[0]
            mujoco.mj_step(self.model, self.data, nstep)
        else:
            for _ in range(nstep):
                self.data.ctrl[:] = rewritten(self.drives, ctrl, self.data.qpos[None], self.data.qvel[None])[0]
                mujoco.mj_step(self.model, self.data)
        mujoco.mj_forward(self.model, self.data)
        self.diverged = np.array([self._divergences() > before])

    def _divergences(self) -> int:
        return sum(int(self.data.warning[code].number) for code in _DIVERGENCE_CODES)

    def arrays(self) -> dict[str, np.ndarray]:
        d = self.data
        return {
            "qpos": d.qpos[None],
            "qvel": d.qvel[None],
            "actuator_force": d.actuator_force[None],
            "sensordata": d.sensordata[None],
            "site_xpos": d.site_xpos[None],
        }

    @property
    def time(self) -> np.ndarray:
        return np.array([self.data.time])


class BatchSimulator:
    """N simulations stepped together on a thread pool (`mujoco.batch.Batch`)."""

    def __init__(self, model: mujoco.MjModel, num_envs: int, nthread: int = 0, drives: Sequence[DriveRewrite] = ()):
        self.model = model
        self.drives = tuple(drives)
        self.num_envs = num_envs
        self.batch = mjbatch.Batch(model, nsim=num_envs, nthread=nthread)
        self.diverged = np.zeros(num_envs, dtype=bool)
        """(N,) which simulations blew up (and were reset by MuJoCo) during the last `step`."""
        self._bound = {
            name: self.batch.bind(name)
            for name in ("qpos", "qvel", "ctrl", "actuator_force", "sensordata", "site_xpos", "time")
        }

    def reset(self, ids: np.ndarray, keyframe: int, qpos: np.ndarray, qvel: np.ndarray) -> None:
        self.batch.reset(ids, keyframe=np.full(len(ids), keyframe), stage=mujoco.mjtStage.mjSTAGE_NONE)
        self._bound["qpos"][ids] = qpos
        self._bound["qvel"][ids] = qvel
        self.batch.forward(ids)

    def step(self, ctrl: np.ndarray, nstep: int) -> None:
        before = self._divergences()
        if not self.drives:
            self._bound["ctrl"][:] = ctrl
            self.batch.step(nstep=nstep, stage=mujoco.mjtStage.mjSTAGE_ACC)
        else:
            # the rewrite reads only the state (qpos, qvel); the derived fields are computed after the last substep
            for i in range(nstep):
                qpos, qvel = np.asarray(self._bound["qpos"]), np.asarray(self._bound["qvel"])
                self._bound["ctrl"][:] = rewritten(self.drives, ctrl, qpos, qvel)
                last = i == nstep - 1
                self.batch.step(nstep=1, stage=mujoco.mjtStage.mjSTAGE_ACC if last else mujoco.mjtStage.mjSTAGE_NONE)
        self.diverged = self._divergences() > before

    def _divergences(self) -> np.ndarray:
        return np.asarray(self.batch.warning[:, _DIVERGENCE_CODES, 1]).sum(1)

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: v for k, v in self._bound.items() if k not in ("ctrl", "time")}

    @property
    def time(self) -> np.ndarray:
        return np.asarray(self._bound["time"]).copy()


def rewritten(drives: Sequence[DriveRewrite], ctrl: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
    """`ctrl` (N, nu) through every drive rewrite in turn, at qpos (N, nq) and qvel (N, nv)."""
    for drive in drives:
        ctrl = drive.control(ctrl, qpos, qvel)
    return ctrl
