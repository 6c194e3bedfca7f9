"""Two interchangeable ways to step N copies of one MuJoCo model: one `MjData` (N = 1) or `mujoco.batch.Batch`.

Both expose the same arrays with a leading batch axis, and both leave every derived quantity computed at the new
state after a step (`mj_forward`), so the single env and the batched env see bit-identical transitions. With a
`DeadBand` (gear backlash) both step one physics step at a time and rewrite the controls before each.
"""

from __future__ import annotations

import mujoco
import numpy as np
from mujoco import batch as mjbatch

from rwm_gym.physics.backlash import DeadBand


class SingleSimulator:
    """One simulation on an `MjData`."""

    num_envs = 1

    def __init__(self, model: mujoco.MjModel, dead_band: DeadBand | None = None):
        self.model = model
        self.data = mujoco.MjData(model)
        self.dead_band = dead_band

    def reset(self, ids: np.ndarray, keyframe: int, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Reset to `keyframe`, then set qpos (n, nq) and qvel (n, nv) of the simulations `ids` (here: [0])."""
        mujoco.mj_resetDataKeyframe(self.model, self.data, keyframe)
        self.data.qpos[:] = qpos[0]
        self.data.qvel[:] = qvel[0]
        mujoco.mj_forward(self.model, self.data)

    def step(self, ctrl: np.ndarray, nstep: int) -> None:
        """Hold ctrl (1, nu) for nstep physics steps (with backlash: rewritten before each, see `DeadBand`)."""
        if self.dead_band is None:
            self.data.ctrl[:] = ctrl[0]
            mujoco.mj_step(self.model, self.data, nstep)
        else:
            for _ in range(nstep):
                self.data.ctrl[:] = self.dead_band.control(ctrl, self.data.qpos[None])[0]
                mujoco.mj_step(self.model, self.data)
        mujoco.mj_forward(self.model, self.data)

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

    def __init__(self, model: mujoco.MjModel, num_envs: int, nthread: int = 0, dead_band: DeadBand | None = None):
        self.model = model
        self.dead_band = dead_band
        self.num_envs = num_envs
        self.batch = mjbatch.Batch(model, nsim=num_envs, nthread=nthread)
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
        if self.dead_band is None:
            self._bound["ctrl"][:] = ctrl
            self.batch.step(nstep=nstep, stage=mujoco.mjtStage.mjSTAGE_ACC)
            return
        for _ in range(nstep):
            self._bound["ctrl"][:] = self.dead_band.control(ctrl, np.asarray(self._bound["qpos"]))
            self.batch.step(nstep=1, stage=mujoco.mjtStage.mjSTAGE_ACC)

    def arrays(self) -> dict[str, np.ndarray]:
        return {k: v for k, v in self._bound.items() if k not in ("ctrl", "time")}

    @property
    def time(self) -> np.ndarray:
        return np.asarray(self._bound["time"]).copy()
