"""Fast physics for a robot of one's own: ANYmal D's solver settings, derived for that robot, measured against the
file's own (`rwm-gym spec --mjcf robot.xml --fast-physics`).

Legged-RL MuJoCo models (MuJoCo Playground's quadrupeds, the shipped ANYmal D and Go2) trade an exact contact solve for
speed: a pyramidal friction cone, a few Newton and line-search iterations, a couple of no-slip iterations, and 4
physics steps per 20 ms policy step. Published models often solve finely instead (Menagerie's Go2: an elliptic cone,
impratio 100, 2 ms steps), which makes PPO in physics several times slower. The rule takes every setting from the
shipped ANYmal D model, so it gives ANYmal D its own settings, and keeps a file's own timestep where that is already
longer than ANYmal D's. `compare` measures what the change costs and buys on the robot itself, and refuses physics that
blows up.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import mujoco
import numpy as np

from rwm_gym.spec import load_spec

SOLVER_FIELDS = ("cone", "impratio", "iterations", "ls_iterations", "noslip_iterations", "integrator")
"""The `mjOption` fields the rule copies from ANYmal D's model, besides the timestep."""

_DIVERGENCE = (mujoco.mjtWarning.mjWARN_BADQACC, mujoco.mjtWarning.mjWARN_BADQVEL, mujoco.mjtWarning.mjWARN_BADQPOS)


def reference_option() -> mujoco.MjOption:
    """The solver options of the shipped ANYmal D model: the settings the rule gives every robot."""
    return mujoco.MjModel.from_xml_path(str(load_spec("anymal_d").model_path)).opt


ROBOT_CONTYPE, ROBOT_CONAFFINITY, WORLD_CONTYPE = 2, 1, 1
"""ANYmal D's collision bits: robot geoms touch the world's (contype 1) and never each other."""


def reference_condim() -> int:
    """The largest contact dimension of ANYmal D's robot geoms (3: sliding friction, no torsion or rolling)."""
    model = mujoco.MjModel.from_xml_path(str(load_spec("anymal_d").model_path))
    return int(max(model.geom_condim[g] for g in range(model.ngeom) if model.geom_bodyid[g] > 0))


def apply_fast_physics(mj: mujoco.MjSpec, own_timestep: float) -> str:
    """Set ANYmal D's solver settings on `mj`, its timestep where the file's is shorter, its contact dimension and its
    collision rule (robot geoms touch the world, never each other); returns what was set."""
    ref = reference_option()
    for name in SOLVER_FIELDS:
        setattr(mj.option, name, getattr(ref, name))
    mj.option.timestep = max(own_timestep, float(ref.timestep))
    condim = reference_condim()
    world = list(mj.worldbody.geoms)  # held, so that mj.geoms hands back these same wrappers (an id() of a freed one
    # could name a robot geom)
    for geom in mj.geoms:
        if not (geom.contype or geom.conaffinity):
            continue  # visual only: stays so
        if any(geom is w for w in world):
            geom.contype |= WORLD_CONTYPE
        else:
            geom.contype, geom.conaffinity = ROBOT_CONTYPE, ROBOT_CONAFFINITY
            geom.condim = min(geom.condim, condim)
    for pair in mj.pairs:  # explicit pairs (MJX-style models) stay, self-contacts included, at that dimension
        pair.condim = min(pair.condim, condim)
    cone = "pyramidal" if int(ref.cone) == int(mujoco.mjtCone.mjCONE_PYRAMIDAL) else "elliptic"
    pairs = f"; the file's {len(mj.pairs)} explicit contact pairs stay" if len(mj.pairs) else ""
    return (
        f"fast physics: ANYmal D's solver ({cone} cone, {ref.iterations} Newton / {ref.ls_iterations} line-search / "
        f"{ref.noslip_iterations} no-slip iterations), a {mj.option.timestep:g} s step (the file's: "
        f"{own_timestep:g} s), contacts of at most {condim} dimensions, and robot geoms that touch the world only"
        f"{pairs}"
    )


@dataclass(frozen=True)
class SolverComparison:
    """The fast physics against the file's own solver on the same robot, same random targets."""

    speedup: float
    """Simulated seconds per wall second, fast over own."""
    step_error: float
    """m/s, RMS difference of the base velocity after one 20 ms policy step from the own solver's states."""
    step_change: float
    """m/s, RMS change of the base velocity over one policy step under the own solver (the scale of the error)."""
    standing_height: tuple[float, float]
    """m, base height after 2 s at the default pose, (own, fast)."""

    def line(self) -> str:
        return (
            f"fast physics measured: {self.speedup:.1f}x the file's solver per simulated second; one 20 ms step from "
            f"the same states differs by {self.step_error:.3f} m/s in base velocity (RMS; the step itself changes it "
            f"by {self.step_change:.3f} m/s); standing height after 2 s {self.standing_height[1]:.3f} m "
            f"(file's solver {self.standing_height[0]:.3f} m)"
        )


def compare(own: mujoco.MjModel, fast: mujoco.MjModel, keyframe: int, seconds: float = 2.0) -> SolverComparison:
    """Run both models from `keyframe` under the same random position targets (0.3 rad around the keyframe's, new
    every 20 ms), then one policy step from each of the own model's states in the fast one. Raises ValueError if the
    fast physics blows up."""
    targets = _targets(own, keyframe, seconds)
    own_states, own_wall = _rollout(own, keyframe, targets)
    fast_states, fast_wall = _rollout(fast, keyframe, targets)
    for _ in range(2):  # the machine may be busy: the best of three timings of each
        own_wall = min(own_wall, _rollout(own, keyframe, targets)[1])
        fast_wall = min(fast_wall, _rollout(fast, keyframe, targets)[1])
    if fast_states is None:
        raise ValueError("the fast physics blows up on this robot (MuJoCo reset it); leave --fast-physics off")
    errors, changes = [], []
    data = mujoco.MjData(fast)
    substeps = max(1, round(0.02 / fast.opt.timestep))
    for k in range(len(targets) - 1):
        qpos, qvel = own_states[k]
        mujoco.mj_resetData(fast, data)
        data.qpos[:], data.qvel[:], data.ctrl[:] = qpos, qvel, targets[k]
        mujoco.mj_step(fast, data, substeps)
        errors.append(data.qvel[:3] - own_states[k + 1][1][:3])
        changes.append(own_states[k + 1][1][:3] - qvel[:3])
    standing = tuple(_standing_height(m, keyframe) for m in (own, fast))
    return SolverComparison(
        speedup=own_wall / max(fast_wall, 1e-9),
        step_error=float(np.sqrt(np.mean(np.square(errors)))),
        step_change=float(np.sqrt(np.mean(np.square(changes)))),
        standing_height=standing,
    )


def _targets(model: mujoco.MjModel, keyframe: int, seconds: float) -> np.ndarray:
    """(policy steps, nu) random targets around the keyframe's joint angles (each actuator's joint), one draw per
    20 ms, seed 0."""
    steps = round(seconds / 0.02)
    pose = model.key_qpos[keyframe][model.jnt_qposadr[model.actuator_trnid[:, 0]]]
    return pose + np.random.default_rng(0).uniform(-0.3, 0.3, (steps, model.nu))


def _rollout(model: mujoco.MjModel, keyframe: int, targets: np.ndarray):
    """([(qpos, qvel)] at each policy step, wall seconds), or (None, wall) if MuJoCo reports a blow-up."""
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, keyframe)
    substeps = max(1, round(0.02 / model.opt.timestep))
    states = []
    start = time.perf_counter()
    for ctrl in targets:
        states.append((data.qpos.copy(), data.qvel.copy()))
        data.ctrl[:] = ctrl
        mujoco.mj_step(model, data, substeps)
    wall = time.perf_counter() - start
    if any(data.warning[int(w)].number for w in _DIVERGENCE):
        return None, wall
    return states, wall


def _standing_height(model: mujoco.MjModel, keyframe: int, seconds: float = 2.0) -> float:
    """m, the base's height after `seconds` with the servos holding the keyframe's joint angles."""
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, keyframe)
    data.ctrl[:] = model.key_qpos[keyframe][model.jnt_qposadr[model.actuator_trnid[:, 0]]]
    mujoco.mj_step(model, data, round(seconds / model.opt.timestep))
    return float(data.qpos[2])
