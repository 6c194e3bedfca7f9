"""Physical parameters of a simulated robot that users (and the sim-to-real workflow) may change.

`PhysicsParams` holds overrides on top of the MJCF and the task spec, each with a physical unit. Every field's neutral
value leaves the model unchanged, so `PhysicsParams()` is the nominal robot. Per-joint fields take one value for all
actuated joints or one value per joint (spec order). Everything here lands in the compiled `MjModel` (MuJoCo holds
actuator delay natively), so the single env, the batched env and `mujoco.sysid` all see the same robot, except
`backlash` and the torque-speed limit, which no MJCF element holds: the simulators apply them (`drive_rewrites`,
`rwm_gym.physics.backlash`, `rwm_gym.physics.torque_speed`), and the sensor biases (`encoder_offset`,
`base_velocity_bias`), which change what the robot reads, not how it moves (`rwm_gym.physics.sensors`). One
field is not physical: `solver`, how exactly MuJoCo solves the robot's contacts, which the gap workflow fits as the
effect `contact_solver` (a simulator whose solver is too coarse misses what the robot does).
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from rwm_gym.options import check_ranges, option
from rwm_gym.physics.backlash import DeadBand
from rwm_gym.physics.torque_speed import TorqueSpeedLimit
from rwm_gym.spec import TaskSpec

PerJoint = float | tuple[float, ...]


@dataclass(frozen=True)
class PhysicsParams:
    """Overrides of the nominal robot; units in the field docs."""

    kp_scale: PerJoint = option(1.0, ge=0, le=100)
    """PD stiffness multiplier on the spec's kp (1)."""
    kd_scale: PerJoint = option(1.0, ge=0, le=100)
    """PD damping multiplier on the spec's kd (1)."""
    motor_strength: PerJoint = option(1.0, ge=0, le=100)
    """Torque gain: the actuator's output torque multiplier (1)."""
    torque_limit: PerJoint | None = option(None, gt=0, le=1e5)
    """Torque saturation (N·m); None keeps the spec's effort limit."""
    joint_friction: PerJoint = option(0.0, ge=0, le=1e4)
    """Coulomb friction torque added at each joint (N·m)."""
    joint_damping: PerJoint = option(0.0, ge=0, le=1e4)
    """Viscous damping added at each joint (N·m·s/rad)."""
    armature: PerJoint = option(0.0, ge=0, le=100)
    """Reflected rotor inertia added at each joint (kg·m²)."""
    action_delay: float = option(0.0, ge=0, le=1)
    """Delay between a position target and its effect in the actuator (s); a multiple of the physics dt."""
    payload_mass: float = option(0.0, ge=-1e4, le=1e4)
    """Point mass added to the base (kg); negative: mass taken from the base body (`lighter_base`), at most
    `MAX_REMOVED_SHARE` of it."""
    payload_com: tuple[float, float, float] = option((0.0, 0.0, 0.0), ge=-10, le=10)
    """Position of the payload (or of the mass taken away) in the base frame (m)."""
    ground_friction: float | None = option(None, ge=0, le=10)
    """Sliding friction coefficient of the floor (1); None keeps the model's."""
    backlash: PerJoint = option(0.0, ge=0, le=1)
    """Total width of the gear dead band between motor and link (rad); an env option, not MJCF (see `backlash`)."""
    torque_speed_slope: PerJoint = option(0.0, ge=0, le=1e4)
    """Fall of each drive's torque limit per rad/s of joint speed above `torque_speed_knee` (N·m·s/rad); an env
    option, not MJCF (see `torque_speed`)."""
    torque_speed_knee: PerJoint = option(1.5, ge=0, le=1e3)
    """Joint speed above which the drive's torque limit falls (rad/s); nothing falls while the slope is 0. The
    default is low for a real drive, but excitation data moves a joint faster than 2 rad/s in a tenth of its rows."""
    ground_solref: tuple[float, float] | None = None
    """MuJoCo solref of the floor's contacts: time constant (s) and damping ratio (1); None keeps the model's."""
    ground_solimp: tuple[float, float, float] | None = None
    """MuJoCo solimp of the floor's contacts: dmin, dmax (1) and width (m); None keeps the model's."""
    encoder_offset: PerJoint = option(0.0, ge=-3.15, le=3.15)
    """Offset of each joint encoder's reading from the joint's position (rad); a sensor bias (see `sensors`)."""
    base_velocity_bias: tuple[float, float, float] = option((0.0, 0.0, 0.0), ge=-10, le=10)
    """Bias of the estimated base linear velocity, base frame (m/s); a sensor bias (see `sensors`)."""
    solver: SolverSettings | None = None
    """Solver settings applied on top of the env's (`SolverSettings`; None: the env's own). Not physics: the gap
    workflow's `contact_solver` effect puts a finer solve here."""

    def __post_init__(self) -> None:
        if isinstance(self.solver, Mapping):
            object.__setattr__(self, "solver", SolverSettings.from_dict(self.solver))
        if not isinstance(self.solver, SolverSettings | None):
            raise ValueError(f"physics parameter 'solver' must be a dict of solver settings, got {self.solver!r}")
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if value is None or isinstance(value, SolverSettings):
                continue
            _check_shape(f.name, str(f.type), value)
            numbers = np.asarray(value)
            if numbers.dtype.kind not in "biuf" or not np.all(np.isfinite(numbers)):
                raise ValueError(f"physics parameter {f.name!r} must be a finite number, got {value!r}")
        check_ranges(self, "physics parameter '{field}'")  # physical ranges: option(ge=..., le=...) above

    @classmethod
    def from_dict(cls, values: Mapping[str, object] | None) -> PhysicsParams:
        """Build from a plain dict (gym.make kwargs, JSON); unknown names raise a one-line error."""
        if not values:
            return cls()
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ValueError(f"unknown physics parameter(s) {unknown}; known: {sorted(names)}")
        return cls(**{k: tuple(v) if isinstance(v, (list, np.ndarray)) else v for k, v in values.items()})

    def to_dict(self) -> dict[str, object]:
        out = {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}
        if out["solver"] is not None:  # only the settings it changes
            out["solver"] = {k: v for k, v in out["solver"].items() if v is not None}
        return out

    def replace(self, **changes: object) -> PhysicsParams:
        return dataclasses.replace(self, **changes)


def _check_shape(name: str, annotation: str, value: object) -> None:
    """A one-line ValueError unless `value` has the shape its field's annotation says: one number (`float`), one
    number or one per joint (`PerJoint`), or exactly N numbers (`tuple[float, ...]` of N)."""
    kind = annotation.replace(" | None", "")
    try:
        shape = np.shape(value)
    except ValueError:  # a ragged list
        shape = None
    if kind == "float" and shape != ():
        raise ValueError(f"physics parameter {name!r} must be one number, got {value!r}")
    if kind == "PerJoint" and (shape is None or len(shape) > 1):
        raise ValueError(f"physics parameter {name!r} must be one number or one per joint, got {value!r}")
    if kind.startswith("tuple[") and shape != (kind.count("float"),):
        raise ValueError(f"physics parameter {name!r} needs {kind.count('float')} numbers, got {value!r}")


def per_joint(value: PerJoint, n: int, name: str) -> np.ndarray:
    """Broadcast a scalar or per-joint value to shape (n,)."""
    out = (
        np.broadcast_to(np.asarray(value, dtype=np.float64), (n,)) if np.ndim(value) == 0 else np.asarray(value, float)
    )
    if out.shape != (n,):
        raise ValueError(f"physics parameter {name!r} has {out.size} values for {n} joints")
    return out


@dataclass(frozen=True)
class SolverSettings:
    """Overrides of the MJCF's constraint-solver `<option>`; None keeps the MJCF's value.

    Not a physical parameter: the robot is the same, only how exactly MuJoCo solves its contacts and joint friction
    changes. The shipped ANYmal MJCF takes 4 solver iterations for speed (PPO); each step then leaves the solve
    unfinished and the next one continues from it, so a trajectory is a rough function of the parameters and the
    start state. Identification (`rwm-gym gap`) and its stand-in for a real robot (`make-measured`) solve each step
    to convergence instead (`CONVERGED_SOLVER`).
    """

    iterations: int | None = None
    """Main solver iterations per physics step (MuJoCo's default 100)."""
    ls_iterations: int | None = None
    """Line-search iterations per solver iteration (MuJoCo's default 50)."""
    noslip_iterations: int | None = None
    """No-slip post-solve iterations (0: off)."""
    cone: str | None = None
    """Friction cone: "pyramidal" or "elliptic" (MuJoCo's default "pyramidal")."""

    @classmethod
    def from_dict(cls, values: Mapping[str, object] | SolverSettings | None) -> SolverSettings:
        if isinstance(values, SolverSettings):
            return values
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values or {}) - names)
        if unknown:
            raise ValueError(f"unknown solver setting(s) {unknown}; known: {sorted(names)}")
        return cls(**dict(values or {}))

    def apply(self, mj: mujoco.MjSpec) -> None:
        if self.cone is not None:
            if self.cone not in CONES:
                raise ValueError(f"solver setting cone must be one of {sorted(CONES)}, got {self.cone!r}")
            mj.option.cone = CONES[self.cone]
        for name in ("iterations", "ls_iterations", "noslip_iterations"):
            value = getattr(self, name)
            if value is not None:
                if value < 0:
                    raise ValueError(f"solver setting {name} must be >= 0, got {value}")
                setattr(mj.option, name, int(value))

    def then(self, other: SolverSettings | None) -> SolverSettings:
        """These settings with `other`'s (where not None) applied on top."""
        if other is None:
            return self
        changes = {
            f.name: getattr(other, f.name) for f in dataclasses.fields(other) if getattr(other, f.name) is not None
        }
        return dataclasses.replace(self, **changes)


CONES: dict[str, int] = {
    "pyramidal": int(mujoco.mjtCone.mjCONE_PYRAMIDAL),
    "elliptic": int(mujoco.mjtCone.mjCONE_ELLIPTIC),
}
"""MuJoCo's friction cones by name (`mjOption.cone`)."""

CONVERGED_SOLVER = SolverSettings(iterations=100, ls_iterations=50)
"""MuJoCo's default iteration counts (no-slip as in the MJCF): each physics step solved to convergence."""


PAYLOAD_INERTIA = 1e-4
"""The payload's principal inertia per kg (m²): a compact point-like mass."""

MAX_REMOVED_SHARE = 0.5
"""The largest share of the base body's mass a negative payload may take away (a battery out, a lighter shell)."""


def lighter_base(
    mass: float, inertia: np.ndarray, com: np.ndarray, removed: float, at: tuple[float, float, float]
) -> tuple[float, np.ndarray, np.ndarray]:
    """The base body's mass (kg), principal inertia (3,) (kg·m²) and centre of mass (3,) (m, base frame) with `removed`
    kg taken away at `at` (base frame): mass and inertia scale by the share left (a uniformly lighter body, so the
    inertia stays physical), and the centre of mass moves as taking a point mass from `at` moves it (the inverse of a
    payload of `removed` kg added there). A one-line ValueError where more than `MAX_REMOVED_SHARE` would go."""
    if removed > MAX_REMOVED_SHARE * mass:
        raise ValueError(
            f"physics parameter 'payload_mass' {-removed:g} kg takes more than {MAX_REMOVED_SHARE:.0%} of the base "
            f"body's {mass:.4g} kg (lowest: {-MAX_REMOVED_SHARE * mass:.4g} kg)"
        )
    left = mass - removed
    return left, np.asarray(inertia) * (left / mass), (mass * np.asarray(com) - removed * np.asarray(at)) / left


def lightest_payload(model: mujoco.MjModel, spec: TaskSpec) -> float:
    """The most negative `payload_mass` (kg) the robot of the compiled nominal `model` allows (0 without a base
    body): `MAX_REMOVED_SHARE` of its base body's mass."""
    base = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, spec.base_body) if spec.base_body else -1
    return -MAX_REMOVED_SHARE * float(model.body_mass[base]) if base >= 0 else 0.0


@dataclass(frozen=True)
class JointFigures:
    """What `params` puts into each actuated joint and its actuator (spec order), and the delay in physics steps."""

    gain: np.ndarray
    """(n,) actuator gainprm[0]: strength * kp."""
    bias: np.ndarray
    """(n, 3) actuator biasprm[:3]: force = gain * target + bias . (1, q, qdot)."""
    limit: np.ndarray
    """(n,) torque saturation (N·m)."""
    friction: np.ndarray
    """(n,) frictionloss added to the MJCF's (N·m)."""
    damping: np.ndarray
    """(n,) damping added to the MJCF's (N·m·s/rad)."""
    armature: np.ndarray
    """(n,) armature added to the MJCF's (kg·m²)."""
    delay_steps: int

    @classmethod
    def of(cls, spec: TaskSpec, params: PhysicsParams) -> JointFigures:
        act = spec.actuator
        n = len(act.joints)
        kp = act.per_joint("kp") * per_joint(params.kp_scale, n, "kp_scale")
        kd = act.per_joint("kd") * per_joint(params.kd_scale, n, "kd_scale")
        strength = per_joint(params.motor_strength, n, "motor_strength")
        limit = per_joint(
            act.per_joint("effort_limit") if params.torque_limit is None else params.torque_limit, n, "torque_limit"
        )
        delay_steps = params.action_delay / spec.physics_dt
        if params.action_delay < 0 or abs(delay_steps - round(delay_steps)) > 1e-6:
            raise ValueError(
                f"action_delay {params.action_delay} s is not a non-negative multiple of {spec.physics_dt} s"
            )
        bias = np.stack([np.zeros(n), -strength * kp, -strength * kd], axis=1)
        return cls(
            strength * kp,
            bias,
            limit,
            per_joint(params.joint_friction, n, "joint_friction"),
            per_joint(params.joint_damping, n, "joint_damping"),
            per_joint(params.armature, n, "armature"),
            int(round(delay_steps)),
        )


def build_model(
    spec: TaskSpec,
    xml_file: str | Path | None = None,
    params: PhysicsParams | None = None,
    solver: SolverSettings | None = None,
) -> mujoco.MjModel:
    """Compile the robot of `spec` (or `xml_file`) with the spec's actuator figures and `params` applied.

    The MJCF must name its actuated hinge joints and their position actuators as the spec's `actuator.joints`.
    """
    return build_spec(spec, xml_file, params, solver).compile()


def build_spec(
    spec: TaskSpec,
    xml_file: str | Path | None = None,
    params: PhysicsParams | None = None,
    solver: SolverSettings | None = None,
) -> mujoco.MjSpec:
    """The uncompiled `MjSpec` of `build_model` (e.g. to write the modified robot as MJCF with `to_xml()`)."""
    params = params or PhysicsParams()
    path = Path(xml_file) if xml_file is not None else spec.model_path
    if not path.is_file():
        raise FileNotFoundError(f"robot model {path} not found")
    try:
        mj = mujoco.MjSpec.from_file(str(path))
    except ValueError as err:  # MuJoCo's parser: its message alone may not say which file
        raise ValueError(f"robot model {path}: MuJoCo cannot load it ({' '.join(str(err).split())})") from None
    if solver is not None:
        solver.apply(mj)
    if params.solver is not None:
        params.solver.apply(mj)
    figures = JointFigures.of(spec, params)
    for i, name in enumerate(spec.actuator.joints):
        actuator, joint = mj.actuator(name), mj.joint(name)
        if actuator is None or joint is None:
            raise ValueError(f"{path}: no joint and position actuator named {name!r} (task spec {spec.name})")
        # Position actuator: force = strength * (kp * (target - q) - kd * qdot), saturated at +-limit.
        actuator.gainprm[0] = figures.gain[i]
        actuator.biasprm[:3] = figures.bias[i]
        actuator.forcelimited = True
        actuator.forcerange = [-figures.limit[i], figures.limit[i]]
        if figures.delay_steps > 0:
            actuator.delay = float(params.action_delay)
            actuator.nsample = figures.delay_steps + 1
        joint.frictionloss += figures.friction[i]
        joint.damping += figures.damping[i]
        joint.armature += figures.armature[i]
    if params.payload_mass > 0:
        base = mj.body(spec.base_body)
        payload = base.add_body(name="payload", pos=list(params.payload_com), mass=params.payload_mass)
        payload.inertia = [PAYLOAD_INERTIA * params.payload_mass] * 3
        payload.explicitinertial = True
        payload.ipos = [0.0, 0.0, 0.0]  # else the compiler places the mass at 2 x payload_com and to_xml drops it
    elif params.payload_mass < 0:
        _lighten_base(mj, spec, params)
    floor_fields = {
        "ground_friction": params.ground_friction,
        "ground_solref": params.ground_solref,
        "ground_solimp": params.ground_solimp,
    }
    if any(v is not None for v in floor_fields.values()):
        floor = mj.geom("floor")
        if floor is None:
            given = ", ".join(k for k, v in floor_fields.items() if v is not None)
            raise ValueError(f"{path}: {given} needs a geom named 'floor'")
        # MuJoCo mixes two geoms' friction by max and their solref/solimp by solmix; a higher priority makes the
        # floor's count alone
        floor.priority = 1
        if params.ground_friction is not None:
            floor.friction[0] = params.ground_friction
        if params.ground_solref is not None:
            floor.solref = ground_solref(params.ground_solref)
        if params.ground_solimp is not None:
            floor.solimp[:3] = ground_solimp(params.ground_solimp)
    return mj


def _lighten_base(mj: mujoco.MjSpec, spec: TaskSpec, params: PhysicsParams) -> None:
    """Write `lighter_base`'s inertial into the base body of `mj` as an explicit one, from the compiled nominal's."""
    nominal = mj.compile()
    b = nominal.body(spec.base_body).id
    mass, inertia, com = lighter_base(
        float(nominal.body_mass[b]),
        nominal.body_inertia[b],
        nominal.body_ipos[b],
        -params.payload_mass,
        params.payload_com,
    )
    base = mj.body(spec.base_body)
    base.explicitinertial = True
    base.mass, base.inertia, base.ipos = mass, list(inertia), list(com)
    base.iquat = list(nominal.body_iquat[b])
    base.fullinertia = [np.nan] + [0.0] * 5  # else the MJCF's fullinertia would stand in for inertia and iquat


def ground_solref(values: tuple[float, float]) -> list[float]:
    """Checked solref (time constant s > 0, damping ratio > 0) of the floor."""
    values = [float(v) for v in np.atleast_1d(values)]
    if len(values) != 2 or min(values) <= 0:
        raise ValueError(f"physics parameter 'ground_solref' needs a time constant and damping ratio > 0, got {values}")
    return values


def ground_solimp(values: tuple[float, float, float]) -> list[float]:
    """Checked solimp (0 < dmin <= dmax < 1, width m > 0) of the floor."""
    values = [float(v) for v in np.atleast_1d(values)]
    if len(values) != 3 or not (0 < values[0] <= values[1] < 1 and values[2] > 0):
        raise ValueError(f"physics parameter 'ground_solimp' needs 0 < dmin <= dmax < 1 and width > 0, got {values}")
    return values


class ModelCache:
    """`build_model` for many parameter sets of one robot, without compiling each.

    Fitting a sim-to-real gap re-simulates hundreds of candidate parameter sets, and compiling each took a sixth of a
    fit's time. Each structure (a payload body or not, delay in physics steps, which floor fields are set, solver
    settings) is compiled once (a negative payload changes the base body's figures, no structure); the figures of
    `params` are written into a copy of it, and `mj_setConst` recomputes what the compiler derives from them (the
    mass matrix at qpos0 that armature enters, the bodies' subtree masses, ...). The result equals
    `build_model(spec, xml_file, params, solver)` field for field, up to rounding (tests/test_gap.py).
    """

    def __init__(self, spec: TaskSpec, xml_file: str | Path | None = None, solver: SolverSettings | None = None):
        self.spec, self.xml_file, self.solver = spec, xml_file, solver
        self._templates: dict[tuple[bool, int, bool, SolverSettings | None], mujoco.MjModel] = {}

    def __call__(self, params: PhysicsParams | None = None) -> mujoco.MjModel:
        params = params or PhysicsParams()
        figures = JointFigures.of(self.spec, params)
        floor = (params.ground_friction is not None, params.ground_solref is not None, params.ground_solimp is not None)
        key = (params.payload_mass > 0, figures.delay_steps, floor, params.solver)
        if key not in self._templates:
            structure = PhysicsParams(
                action_delay=params.action_delay,
                payload_mass=1.0 if key[0] else 0.0,
                ground_friction=1.0 if floor[0] else None,
                ground_solref=(0.02, 1.0) if floor[1] else None,
                ground_solimp=(0.9, 0.95, 0.001) if floor[2] else None,
                solver=params.solver,
            )
            self._templates[key] = build_model(self.spec, self.xml_file, structure, self.solver)
        template = self._templates[key]
        model = copy.copy(template)
        obj = mujoco.mjtObj
        actuators = [mujoco.mj_name2id(model, obj.mjOBJ_ACTUATOR, n) for n in self.spec.actuator.joints]
        dofs = model.jnt_dofadr[[mujoco.mj_name2id(model, obj.mjOBJ_JOINT, n) for n in self.spec.actuator.joints]]
        model.actuator_gainprm[actuators, 0] = figures.gain
        model.actuator_biasprm[actuators, :3] = figures.bias
        model.actuator_forcerange[actuators] = np.stack([-figures.limit, figures.limit], axis=1)
        model.dof_frictionloss[dofs] = template.dof_frictionloss[dofs] + figures.friction
        model.dof_damping[dofs] = template.dof_damping[dofs] + figures.damping
        model.dof_dampingpoly[dofs] = template.dof_dampingpoly[dofs] + figures.damping[:, None]
        model.dof_armature[dofs] = template.dof_armature[dofs] + figures.armature
        if key[0]:
            body = mujoco.mj_name2id(model, obj.mjOBJ_BODY, "payload")
            model.body_mass[body] = params.payload_mass
            model.body_inertia[body] = PAYLOAD_INERTIA * params.payload_mass
            model.body_pos[body] = params.payload_com
        elif params.payload_mass < 0:
            base = model.body(self.spec.base_body).id
            model.body_mass[base], model.body_inertia[base], model.body_ipos[base] = lighter_base(
                float(template.body_mass[base]),
                template.body_inertia[base],
                template.body_ipos[base],
                -params.payload_mass,
                params.payload_com,
            )
        floor_geom = mujoco.mj_name2id(model, obj.mjOBJ_GEOM, "floor")
        if floor[0]:
            model.geom_friction[floor_geom, 0] = params.ground_friction
        if floor[1]:
            model.geom_solref[floor_geom] = ground_solref(params.ground_solref)
        if floor[2]:
            model.geom_solimp[floor_geom, :3] = ground_solimp(params.ground_solimp)
        mujoco.mj_setConst(model, mujoco.MjData(model))
        # The compiler's statistics that mj_setConst leaves alone; the solver scales its tolerance by meaninertia.
        model.stat.meaninertia = model.dof_M0.mean()
        model.stat.meanmass = model.body_mass[1:].mean()
        return model


def dead_band(spec: TaskSpec, model: mujoco.MjModel, params: PhysicsParams | None) -> DeadBand | None:
    """The backlash of `params` on `model`'s actuated joints, for the simulators; None without backlash."""
    if params is None:
        return None
    width = per_joint(params.backlash, len(spec.actuator.joints), "backlash")
    return DeadBand.from_model(model, spec.actuator.joints, width)


def drive_rewrites(
    spec: TaskSpec, model: mujoco.MjModel, params: PhysicsParams | None
) -> tuple[DeadBand | TorqueSpeedLimit, ...]:
    """What the simulators apply to `model`'s controls for `params` before every physics step, in order: the dead
    band of backlash on the position error, then the torque-speed limit on the force that leaves."""
    if params is None:
        return ()
    n = len(spec.actuator.joints)
    limit = TorqueSpeedLimit.from_model(
        model,
        spec.actuator.joints,
        per_joint(params.torque_speed_slope, n, "torque_speed_slope"),
        per_joint(params.torque_speed_knee, n, "torque_speed_knee"),
    )
    return tuple(d for d in (dead_band(spec, model, params), limit) if d is not None)
