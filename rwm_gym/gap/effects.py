"""The vocabulary of physical effects a simulator may miss, each a parametric change of `PhysicsParams` with units.

An `Effect` maps a small parameter vector (1-3 numbers, physical units) to `PhysicsParams` overrides. The gap workflow
fits every effect of `vocabulary(spec)` to measured data and names those that explain the gap; `make-measured` hides
one (or several) in a simulator. The effects here act globally (the same value on all 12 joints); `rwm_gym.gap.scope`
derives per-leg, per-joint-type and per-joint forms of the joint effects. `PhysicsParams` itself takes per-joint
values, which `make-measured --physics` can hide.

Backlash is a dead band of the position error at the physics rate (`rwm_gym.physics.backlash`), and the torque-speed
limit a clip of the drive's force that falls with joint speed (`rwm_gym.physics.torque_speed`); the corrected MJCF
cannot hold either, so they live in the corrected env options. Ground compliance is the floor's MuJoCo solref
(`PhysicsParams.ground_solref`; its solimp can be hidden with `make-measured --physics`, not fitted).

Two effects act on the measurement, not the dynamics (`rwm_gym.physics.sensors`): an encoder offset on every joint
position read and a bias of the estimated base linear velocity. The measured data holds readings, as it holds the
sensor noise; the re-simulation undoes a candidate bias on each measured start state and applies it to each
simulated one, so a sensor bias is fitted, charged and named like any physical effect.

`contact_solver` is no property of the robot but of the simulator: its constraint solver (iterations, no-slip
iterations, friction cone) solves contacts and joint friction too coarsely to follow the robot. Its nominal values
are the simulator's own settings (the `solver` the vocabulary is built for), so the gap of the simulator as the user
runs it is measured first, and a finer solve must earn its three parameters like any other effect.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from rwm_gym.physics.params import (
    CONES,
    CONVERGED_SOLVER,
    PhysicsParams,
    SolverSettings,
    build_model,
    lightest_payload,
)
from rwm_gym.spec import TaskSpec


@dataclass(frozen=True)
class Parameter:
    """One fitted number of an effect."""

    name: str
    unit: str
    nominal: float
    """Value of the nominal simulator (the effect is absent)."""
    low: float
    high: float
    """Plausible range searched by the fit."""
    default: float
    """A realistic magnitude, used by `make-measured` when no magnitude is given."""
    step: float = 0.0
    """Resolution of a discrete parameter (0: continuous)."""


@dataclass(frozen=True)
class Effect:
    """A candidate physical effect: parameters in physical units and how they change the simulator."""

    name: str
    description: str
    parameters: tuple[Parameter, ...]
    apply: Callable[[np.ndarray], dict[str, object]]
    """Parameter vector (P,) -> `PhysicsParams` field overrides."""
    scope: str = "global"
    nested_in: tuple[str, ...] = ()
    """Effects that contain this one as a special case (equal fit there: the simpler one is named)."""
    fit_on_mean: bool = False
    """Refined on the training windows' mean residual, not on each window's (`fit.fit_effect`): a bias read into
    every window's start shifts all windows alike, while each window's squared error follows how its contacts answer
    the shifted start. For a base-velocity bias at 0.5x that squared error is flat within 3 % from 0.7x to 1.2x the
    bias, and the mean residual crosses zero within 2 % of it."""

    @property
    def nominal(self) -> np.ndarray:
        return np.array([p.nominal for p in self.parameters])

    @property
    def magnitude_name(self) -> str:
        """The parameter whose value is "the magnitude" of the effect (the first)."""
        return self.parameters[0].name

    def physics(self, values: Sequence[float], base: PhysicsParams | None = None) -> PhysicsParams:
        """`base` (default nominal) with this effect at `values` applied on top."""
        return (base or PhysicsParams()).replace(**self.apply(np.asarray(values, float)))

    def values_from_magnitude(self, magnitude: Sequence[float] | float) -> np.ndarray:
        """Full parameter vector from a magnitude (first parameters given, the rest nominal)."""
        given = np.atleast_1d(np.asarray(magnitude, float))
        if len(given) > len(self.parameters):
            raise ValueError(f"effect {self.name!r} has {len(self.parameters)} parameter(s), got {len(given)} values")
        values = self.nominal.copy()
        values[: len(given)] = given
        return values


TORQUE_SPEED_KNEE = PhysicsParams().torque_speed_knee
"""rad/s, the knee of the `torque_speed_limit` effect where only its slope is given (`PhysicsParams`' default)."""

SOLVER_ITERATION_STEP = 4
"""Resolution of the `contact_solver` effect's iteration count (a step of 1 would cost a re-simulation per count)."""

NOSLIP_RANGE = (0, 8, 2)
"""Lowest, highest and step of the `contact_solver` effect's no-slip iterations."""


def solver_effect(model: mujoco.MjModel) -> Effect:
    """`contact_solver` for a simulator whose compiled `model` holds its solver settings (the nominal values)."""
    opt = model.opt
    iterations, noslip = int(opt.iterations), int(opt.noslip_iterations)
    elliptic = float(opt.cone == CONES["elliptic"])
    most = max(iterations, int(CONVERGED_SOLVER.iterations))
    line_search = max(int(opt.ls_iterations), int(CONVERGED_SOLVER.ls_iterations))
    lo, hi, step = NOSLIP_RANGE

    def apply(v: np.ndarray) -> dict[str, object]:
        n, slip, cone = round(float(v[0])), round(float(v[1])), float(v[2]) >= 0.5
        if (n, slip, cone) == (iterations, noslip, bool(elliptic)):
            return {"solver": None}
        return {
            "solver": SolverSettings(
                iterations=n,
                ls_iterations=line_search if n != iterations else int(opt.ls_iterations),
                noslip_iterations=slip,
                cone="elliptic" if cone else "pyramidal",
            )
        }

    return Effect(
        "contact_solver",
        "the simulator's constraint solver too coarse: more iterations, no-slip iterations or the elliptic cone",
        (
            Parameter("solver_iterations", "1", iterations, iterations, most, most, step=SOLVER_ITERATION_STEP),
            Parameter("noslip_iterations", "1", noslip, min(lo, noslip), max(hi, noslip), noslip, step=step),
            Parameter("elliptic_cone", "1", elliptic, 0.0, 1.0, elliptic, step=1.0),
        ),
        apply,
    )


def _scaled_limits(limits: np.ndarray, strongest: float) -> float | tuple[float, ...]:
    """Per-joint torque limits with the strongest drive's at `strongest` N·m (one number where all are equal)."""
    if np.all(limits == limits[0]):
        return strongest
    return tuple(float(x) for x in limits * (strongest / limits.max()))


def vocabulary(
    spec: TaskSpec, xml_file: str | Path | None = None, solver: SolverSettings | None = None
) -> dict[str, Effect]:
    """Every effect the workflow knows, with nominal values and ranges resolved against the task spec (effort limit,
    physics dt), the robot model (floor friction, the base body's mass a lighter robot lacks) and the simulator's
    `solver` (None: the MJCF's)."""
    limits, dt = spec.actuator.per_joint("effort_limit"), spec.physics_dt
    limit = float(limits.max())  # the strongest drive's; weaker drives scale with it
    model = build_model(spec, xml_file, solver=solver)
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    mu = float(model.geom_friction[floor, 0]) if floor >= 0 else 1.0
    solref = [float(x) for x in model.geom_solref[floor]] if floor >= 0 else [0.02, 1.0]
    effects = (
        Effect(
            "action_delay",
            "dead time between a position target and the actuator acting on it",
            (Parameter("action_delay", "s", 0.0, 0.0, 8 * dt, 3 * dt, step=dt),),
            lambda v: {"action_delay": round(float(v[0]) / dt) * dt},
        ),
        Effect(
            "joint_friction",
            "Coulomb friction torque in every joint (gearbox, seals)",
            (Parameter("joint_friction", "N·m", 0.0, 0.0, 8.0, 2.0),),
            lambda v: {"joint_friction": float(v[0])},
        ),
        Effect(
            "joint_damping",
            "viscous damping torque in every joint, proportional to joint velocity",
            (Parameter("joint_damping", "N·m·s/rad", 0.0, 0.0, 5.0, 1.0),),
            lambda v: {"joint_damping": float(v[0])},
        ),
        Effect(
            "armature",
            "reflected rotor inertia of every drive (rotor inertia x gear ratio^2)",
            (Parameter("armature", "kg·m²", 0.0, 0.0, 0.3, 0.05),),
            lambda v: {"armature": float(v[0])},
        ),
        Effect(
            "motor_strength",
            "torque gain of every drive: output torque = gain x commanded torque",
            (Parameter("motor_strength", "1", 1.0, 0.4, 1.6, 0.8),),
            lambda v: {"motor_strength": float(v[0])},
            nested_in=("pd_gains",),
        ),
        Effect(
            "torque_limit",
            "saturation torque of every drive, lower than the data sheet's (the strongest drive's, in N·m)",
            (Parameter("torque_limit", "N·m", limit, 0.1 * limit, limit, 0.4 * limit),),
            lambda v: {"torque_limit": _scaled_limits(limits, float(v[0]))},
        ),
        Effect(
            "pd_gains",
            "PD gain mismatch of the joint controllers: kp and kd scaled separately",
            (Parameter("kp_scale", "1", 1.0, 0.4, 1.6, 0.7), Parameter("kd_scale", "1", 1.0, 0.2, 3.0, 1.0)),
            lambda v: {"kp_scale": float(v[0]), "kd_scale": float(v[1])},
        ),
        Effect(
            "payload",
            "unmodelled point mass on the base at a horizontal offset from the base origin (negative: mass the base "
            "body lacks, a robot lighter than its model)",
            (
                Parameter("payload_mass", "kg", 0.0, lightest_payload(model, spec), 30.0, 8.0),
                Parameter("payload_com_x", "m", 0.0, -0.4, 0.4, 0.1),
                Parameter("payload_com_y", "m", 0.0, -0.2, 0.2, 0.0),
            ),
            lambda v: {"payload_mass": float(v[0]), "payload_com": (float(v[1]), float(v[2]), 0.0)},
        ),
        Effect(
            "ground_friction",
            "sliding friction coefficient of the floor",
            (Parameter("ground_friction", "1", mu, 0.05, max(mu, 1.0), 0.3 * mu),),
            lambda v: {"ground_friction": float(v[0])},
        ),
        Effect(
            "backlash",
            "gear dead band of total width b between motor and link in every drive",
            (Parameter("backlash", "rad", 0.0, 0.0, 0.08, 0.03),),
            lambda v: {"backlash": float(v[0])},
        ),
        Effect(
            "torque_speed_limit",
            "drive torque limit falling linearly with joint speed above a knee (back-EMF of the motors)",
            (
                Parameter("torque_speed_slope", "N·m·s/rad", 0.0, 0.0, 40.0, 15.0),
                Parameter("torque_speed_knee", "rad/s", TORQUE_SPEED_KNEE, 0.0, 6.0, TORQUE_SPEED_KNEE),
            ),
            lambda v: {"torque_speed_slope": float(v[0]), "torque_speed_knee": float(v[1])},
        ),
        Effect(
            "ground_compliance",
            "soft or springy floor: time constant and damping ratio of MuJoCo's solref of the floor's contacts",
            (
                Parameter("ground_timeconst", "s", solref[0], 2 * dt, 0.1, 0.05),
                Parameter("ground_dampratio", "1", solref[1], 0.2, 2.0, solref[1]),
            ),
            lambda v: {"ground_solref": (float(v[0]), float(v[1]))},
        ),
        Effect(
            "encoder_offset",
            "joint encoders read off their joints' positions by a constant offset (a sensor bias: no dynamics)",
            (Parameter("encoder_offset", "rad", 0.0, -0.1, 0.1, 0.03),),
            lambda v: {"encoder_offset": float(v[0])},
        ),
        Effect(
            "base_velocity_bias",
            "the state estimator's base linear velocity off by a constant, base frame (a sensor bias: no dynamics)",
            (
                Parameter("base_velocity_bias_x", "m/s", 0.0, -0.3, 0.3, 0.1),
                Parameter("base_velocity_bias_y", "m/s", 0.0, -0.3, 0.3, 0.0),
                Parameter("base_velocity_bias_z", "m/s", 0.0, -0.3, 0.3, 0.0),
            ),
            lambda v: {"base_velocity_bias": (float(v[0]), float(v[1]), float(v[2]))},
            fit_on_mean=True,
        ),
        solver_effect(model),
    )
    return {e.name: e for e in effects}


EFFECT_NAMES: tuple[str, ...] = (
    "action_delay",
    "joint_friction",
    "joint_damping",
    "armature",
    "motor_strength",
    "torque_limit",
    "pd_gains",
    "payload",
    "ground_friction",
    "backlash",
    "torque_speed_limit",
    "ground_compliance",
    "encoder_offset",
    "base_velocity_bias",
    "contact_solver",
)
"""The vocabulary's names, in report order (`vocabulary(spec)` has the same keys)."""


def parse_effects(spec: TaskSpec, names: Sequence[str], magnitudes: Sequence[str] | None) -> dict[str, np.ndarray]:
    """Pair `--effect` names with `--magnitude` strings ("2.0" or "0.7,1.2"; missing: the realistic default)."""
    effects = vocabulary(spec)
    magnitudes = list(magnitudes or [])
    if len(magnitudes) > len(names):
        raise ValueError(f"{len(magnitudes)} --magnitude values for {len(names)} --effect names")
    out: dict[str, np.ndarray] = {}
    for i, name in enumerate(names):
        if name not in effects:
            raise ValueError(f"unknown effect {name!r}; vocabulary: {', '.join(EFFECT_NAMES)}")
        effect = effects[name]
        if i < len(magnitudes):
            out[name] = effect.values_from_magnitude([float(x) for x in magnitudes[i].split(",")])
        else:
            out[name] = np.array([p.default for p in effect.parameters])
    return out


def combined_physics(
    effects: Mapping[str, Sequence[float]], spec: TaskSpec, base: PhysicsParams | None = None
) -> PhysicsParams:
    """`base` with every effect of `effects` ({name: values}) applied in turn."""
    params, known = base or PhysicsParams(), vocabulary(spec)
    for name, values in effects.items():
        params = known[name].physics(values, params)
    return params
