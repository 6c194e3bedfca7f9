"""`rwm-gym make-measured`: "measured" data from a simulator with hidden physical effects, for demos and tests.

The data is collected from the nominal robot with one or more effects of the vocabulary (`rwm_gym.gap.effects`)
added, driven by `--policy` (the excitation policy made for identification, or an ordinary one: the scripted gait,
random actions, or a trained SB3 policy walking on commands, as a real robot's log would be), then given small sensor
noise and written in exactly the dataset format a converted robot log has: the env id
is the nominal simulator's, `physics_params` is empty (unknown), the policy is "unknown" and the metadata is empty.
Nothing in the file names the effect; the workflow has to find it.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import mujoco
import numpy as np

from rwm_gym.data.collect import collect, diverged_episodes, make_physics_core
from rwm_gym.data.dataset import Dataset, write_dataset
from rwm_gym.gap.effects import combined_physics
from rwm_gym.options import check_ranges, option
from rwm_gym.physics.params import CONVERGED_SOLVER, SolverSettings
from rwm_gym.physics.robot import measure
from rwm_gym.policies.excitation import ExcitationPolicy
from rwm_gym.policies.factory import make_policy


@dataclass(frozen=True)
class SensorNoise:
    """Std of Gaussian sensor noise per measured quantity (SI units); `scale` multiplies all of them."""

    joint_pos: float = option(2e-4, ge=0)
    """rad, joint encoders."""
    joint_vel: float = option(0.02, ge=0)
    """rad/s, differentiated encoders."""
    joint_torque: float = option(0.3, ge=0)
    """N·m, drive current -> torque."""
    base_lin_vel: float = option(0.02, ge=0)
    """m/s, state estimator."""
    base_ang_vel: float = option(0.01, ge=0)
    """rad/s, IMU gyro."""
    base_orientation: float = option(0.002, ge=0)
    """rad, IMU attitude."""
    scale: float = option(1.0, ge=0)

    def __post_init__(self) -> None:
        check_ranges(self, "sensor noise {field}")  # a std: finite and >= 0


def add_sensor_noise(episode: dict[str, np.ndarray], core, noise: SensorNoise, rng: np.random.Generator) -> None:
    """Perturb qpos/qvel/torque of one episode in place and rebuild its state from them (so the two agree)."""
    if noise.scale == 0:
        return
    torque = episode["state"][:, core.spec.state_slices["joint_torque"]]
    episode["qpos"], episode["qvel"], episode["state"] = noisy_measurement(
        core.layout, core.spec, core.model, episode["qpos"], episode["qvel"], torque, noise, rng
    )


def noisy_measurement(
    layout,
    spec,
    model,
    qpos: np.ndarray,
    qvel: np.ndarray,
    joint_torque: np.ndarray,
    noise: SensorNoise,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sensor readings of true rows: noisy copies of qpos (N, nq), qvel (N, nv) and the state (N, S) built from them
    and the noisy joint torque (N, A). The noise floor of the gap workflow draws its noise here too."""
    qpos, qvel = np.array(qpos, float), np.array(qvel, float)
    rows, s = len(qpos), noise.scale
    qpos[:, layout.qpos_adr] += rng.normal(0, s * noise.joint_pos, (rows, len(layout.qpos_adr)))
    qvel[:, layout.dof_adr] += rng.normal(0, s * noise.joint_vel, (rows, len(layout.dof_adr)))
    qvel[:, 0:3] += rng.normal(0, s * noise.base_lin_vel, (rows, 3))
    qvel[:, 3:6] += rng.normal(0, s * noise.base_ang_vel, (rows, 3))
    for t in range(rows):  # a small random rotation of the base orientation
        quat = qpos[t, 3:7].copy()
        mujoco.mju_quatIntegrate(quat, rng.normal(0, s * noise.base_orientation, 3), 1.0)
        qpos[t, 3:7] = quat
    torque = np.zeros((rows, model.nu))
    torque[:, layout.actuator_ids] = joint_torque
    torque[:, layout.actuator_ids] += rng.normal(0, s * noise.joint_torque, (rows, len(layout.actuator_ids)))
    sensors, sites = np.zeros((rows, model.nsensordata)), np.zeros((rows, model.nsite, 3))
    return qpos, qvel, measure(layout, spec, qpos, qvel, torque, sensors, sites).state


def make_measured(
    effects: Mapping[str, Sequence[float]],
    episodes: int,
    out: str | Path,
    *,
    env_id: str = "AnymalD-MuJoCo-v0",
    env_kwargs: Mapping[str, object] | None = None,
    extra_physics: Mapping[str, object] | None = None,
    seed: int = 0,
    max_steps: int = 250,
    num_envs: int = 8,
    noise: SensorNoise = SensorNoise(),
    policy: str = "excitation",
    solver: SolverSettings | None = CONVERGED_SOLVER,
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Write `episodes` episodes of `env_id` with `effects` ({name: parameter values}) hidden in the robot.

    `extra_physics` (PhysicsParams fields, e.g. per-joint values) is hidden too. `policy` drives the robot:
    `excitation` (default), `gait`, `random` or the path of an SB3 `.zip`. `solver`: how the robot's physics is
    solved (default: each step to convergence, as a real robot's physics is; None: the MJCF's own settings). Where
    that physics blows up in any episode (the MJCF's 4 iterations on ice, ground friction 0.05), the data show no
    robot's motion: a ValueError says so and nothing is written; so does a hidden robot that cannot be built (a
    negative payload heavier than half the base body).
    """
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out}: file exists (pass --overwrite to replace it)")
    env_kwargs = dict(env_kwargs or {})
    nominal = make_physics_core(env_id, 1, **env_kwargs)
    hidden = combined_physics(effects, nominal.spec, nominal.params.replace(**dict(extra_physics or {})))
    make_physics_core(env_id, 1, **{**env_kwargs, "physics": hidden})  # a robot that cannot be built: before any file
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, raw = tempfile.mkstemp(suffix=".h5", dir=out.parent)
    os.close(fd)
    try:
        n = max(1, min(num_envs, episodes))
        driver = ExcitationPolicy(nominal.spec, n) if policy == "excitation" else make_policy(policy, nominal.spec, n)
        solved = {"solver": asdict(solver)} if solver is not None else {}
        collect(
            env_id,
            driver,
            episodes,
            raw,
            seed=seed,
            num_envs=num_envs,
            max_steps=max_steps,
            env_kwargs={**env_kwargs, "physics": hidden, **solved},
            overwrite=True,
            progress=progress,
        )
        source = Dataset.load(raw)
        blown = diverged_episodes(source)
        if len(blown):
            raise ValueError(
                f"the stand-in robot's physics blew up in {len(blown)} of {source.num_episodes} episodes (MuJoCo "
                "reset the simulation): no measurement of a robot; solve it to convergence (the default solver)"
            )
        info = replace(
            source.info, env_id=env_id, policy="unknown", seed=0, physics_params={}, metadata={}, complete=False
        )
        rng = np.random.default_rng([seed, 7])

        def noisy_episodes():
            for e in range(source.num_episodes):
                episode = {k: np.array(v) for k, v in source.episode(e).items()}
                add_sensor_noise(episode, nominal, noise, rng)
                yield episode

        write_dataset(out, info, noisy_episodes())
    finally:
        Path(raw).unlink(missing_ok=True)
    return out


def write_spring_model(
    spec, out: str | Path, joint_type: str, stiffness: float, xml_file: str | Path | None = None
) -> Path:
    """An effect outside the vocabulary, for benchmarks and tests: the robot's MJCF with a torsion spring
    (`stiffness` N·m/rad, rest at the default pose) in every actuated joint whose name ends in `joint_type`, edited
    into the MuJoCo model directly (no `PhysicsParams` field can express it). Writes a standalone MJCF at `out`."""
    mj = mujoco.MjSpec.from_file(str(xml_file or spec.model_path))
    hit = 0
    for name, rest in zip(spec.actuator.joints, spec.actuator.default_pose):
        if name.endswith(joint_type):
            joint = mj.joint(name)
            joint.stiffness = [float(stiffness), 0.0, 0.0]  # linear spring: polynomial coefficients
            joint.springref = float(rest)
            hit += 1
    if not hit:
        raise ValueError(f"no actuated joint name ends in {joint_type!r}")
    from rwm_gym.atomic import write_text

    return write_text(out, mj.to_xml())


def solver_option(iterations: int) -> SolverSettings | None:
    """--solver-iterations N: N iterations (line search as `CONVERGED_SOLVER`); 0: the MJCF's own settings."""
    if iterations < 0:
        raise ValueError(f"--solver-iterations must be >= 0, got {iterations}")
    return replace(CONVERGED_SOLVER, iterations=iterations) if iterations else None
