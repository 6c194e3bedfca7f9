"""The task spec: one TOML file per environment in `envs/`, read into frozen dataclasses.

The spec is the single place where a task's numbers live (layouts, normalisation, reward weights, command ranges, dt,
actuator figures). Its text is stored verbatim in every dataset and checkpoint, so a file can always be matched to
the task it came from.
"""

from __future__ import annotations

import tomllib
from dataclasses import asdict, dataclass, field
from functools import cached_property
from importlib.metadata import version
from pathlib import Path

import numpy as np

from rwm_gym.resources import model_file, specs_dir


@dataclass(frozen=True)
class Group:
    """A named block of consecutive columns with its normalisation, e.g. `joint_vel` (12 columns, rad/s)."""

    name: str
    columns: tuple[str, ...]
    unit: str
    mean: tuple[float, ...]
    std: tuple[float, ...]

    @property
    def size(self) -> int:
        return len(self.columns)


PerJointFigure = float | tuple[float, ...]
"""One value for every actuated joint, or one per joint in `ActuatorSpec.joints` order."""


@dataclass(frozen=True)
class ActuatorSpec:
    """The actuated joints and their position servos (spec `[actuator]`).

    `kp`, `kd`, `effort_limit` and `velocity_limit` take one number for every joint or a list with one per joint
    (a Go2's knees are stronger than its hips); `per_joint` gives either as an array.
    """

    joints: tuple[str, ...]
    default_pose: tuple[float, ...]
    """rad, one per joint."""
    action_scale: float
    """rad per unit action; actions live in [-1, 1]."""
    kp: PerJointFigure
    """N·m/rad."""
    kd: PerJointFigure
    """N·m·s/rad."""
    effort_limit: PerJointFigure
    """N·m."""
    velocity_limit: PerJointFigure
    """rad/s."""

    def per_joint(self, name: str) -> np.ndarray:
        """(A,) the figure `name` ("kp", "kd", "effort_limit", "velocity_limit") of each joint."""
        return np.broadcast_to(np.asarray(getattr(self, name), dtype=np.float64), (len(self.joints),)).copy()


def _figure(act: dict, key: str, default: float, n: int, where: str) -> PerJointFigure:
    """A spec `[actuator]` figure: a number, or a list of one per joint."""
    value = act.get(key, default)
    if isinstance(value, list):
        if len(value) != n:
            raise ValueError(f"{where}: actuator.{key} has {len(value)} values for {n} joints")
        return tuple(float(v) for v in value)
    return float(value)


@dataclass(frozen=True)
class PrivilegedSpec:
    """The bodies whose contacts, heights and falls the world model predicts (spec `[privileged]`)."""

    contact_bodies: tuple[str, ...]
    contact_threshold: float
    """N: a body is in contact when its net contact force exceeds this."""
    feet: tuple[str, ...]
    thighs: tuple[str, ...]
    termination_bodies: tuple[str, ...]
    foot_height_std: float
    """m, normalisation of foot heights for the world model."""


@dataclass(frozen=True)
class CommandSpec:
    """The velocity commands: names, uniform ranges, resampling period (s) and standing share (spec `[command]`)."""

    names: tuple[str, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]
    resample_seconds: float
    standing_fraction: float
    standing_threshold: float


@dataclass(frozen=True)
class RewardSpec:
    """The reward terms' weights and shaping constants (spec `[reward]`)."""

    weights: dict[str, float]
    tracking_sigma: float
    feet_air_time_target: float
    base_height_target: float = float("nan")
    """m, the base height the `base_height` term pulls toward (a biped's; NaN where the spec gives none)."""


@dataclass(frozen=True)
class ObservationSpec:
    """The policy observation's groups, in order, and their noise (spec `[observation]`)."""

    groups: tuple[str, ...]
    noise: dict[str, float]


@dataclass(frozen=True)
class ResetSpec:
    """Uniform perturbations of the keyframe at reset (half-widths)."""

    joint_pos_noise: float = 0.0
    """rad."""
    base_lin_vel_noise: float = 0.0
    """m/s."""
    base_ang_vel_noise: float = 0.0
    """rad/s."""


@dataclass(frozen=True)
class SymmetrySpec:
    """The robot's left-right mirror (the `[symmetry]` table), for mirrored copies of observations and actions.

    A vector indexed by joints (joint_pos, the action, ...) mirrors as `mirrored[i] = joint_signs[i] * x[j]` where
    `joints[i]` is the j-th actuated joint; any other group mirrors column by column with `signs[group]`.
    """

    joints: tuple[str, ...]
    """The joint each actuated joint maps to, in `actuator.joints` order (e.g. LF_HAA -> RF_HAA)."""
    joint_signs: tuple[float, ...]
    """+1 or -1 per actuated joint: the sign its angle takes on the mirror joint."""
    signs: dict[str, tuple[float, ...]]
    """+1 or -1 per column of each non-joint group of the state or observation (e.g. base_lin_vel: 1, -1, 1)."""


@dataclass(frozen=True)
class SuiteTask:
    """The `[dm_control]` table of a spec: which suite task runs, and which body counts as the contact partner."""

    domain: str
    """dm_control suite domain, e.g. "cheetah"."""
    task: str
    """Task of the domain, e.g. "run"."""
    contact_partner: str = "world"
    """Body whose contacts with `privileged.contact_bodies` set the contact flags ("world" holds the floor)."""

    @classmethod
    def from_spec(cls, spec: TaskSpec) -> SuiteTask:
        table = spec.extra.get("dm_control")
        if not isinstance(table, dict):
            raise ValueError(f"task spec {spec.name}: missing table [dm_control] (domain, task)")
        for key in ("domain", "task"):
            if not isinstance(table.get(key), str):
                raise ValueError(f"task spec {spec.name}: [dm_control] field {key!r} missing or not a string")
        unknown = sorted(set(table) - {"domain", "task", "contact_partner"})
        if unknown:
            raise ValueError(f"task spec {spec.name}: [dm_control] unknown field {unknown[0]!r}")
        return cls(**table)

    def to_dict(self) -> dict:
        """JSON-serialisable description stored with datasets as their `physics_params`."""
        return {**asdict(self), "dm_control_version": version("dm-control")}


@dataclass(frozen=True)
class TaskSpec:
    """A task: robot model, state and privileged layouts, observation, commands, reward, timing."""

    name: str
    physics_env_id: str
    imagined_env_id: str
    model: str
    """MJCF path relative to `assets/` (or absolute); empty when the simulator ships its own (dm_control)."""
    policy_dt: float
    physics_dt: float
    episode_steps: int
    keyframe: str
    base_body: str
    actuator: ActuatorSpec
    state: tuple[Group, ...]
    privileged: PrivilegedSpec
    observation: ObservationSpec
    command: CommandSpec
    reward: RewardSpec
    reset: ResetSpec
    text: str = field(repr=False, compare=False)
    """The TOML source, stored in datasets and checkpoints."""
    extra: dict = field(default_factory=dict, repr=False, compare=False)
    """Tables of the TOML this class does not type (task-specific sections, e.g. dm_control's)."""
    default_checkpoint: str = ""
    """World-model checkpoint shipped for the imagined env, relative to `assets/` (empty: none ships)."""
    symmetry: SymmetrySpec | None = None
    """The robot's left-right mirror (None: the spec has no `[symmetry]` table)."""
    model_dir: Path | None = field(default=None, repr=False, compare=False)
    """Folder besides `assets/` where `model` may lie: the folder of a spec file the user gave (None for a spec read
    from a dataset or checkpoint, which names only the package's own models)."""

    @property
    def substeps(self) -> int:
        return int(round(self.policy_dt / self.physics_dt))

    @property
    def model_path(self) -> Path:
        """The MJCF file `model` names, inside `assets/` or `model_dir`, checked (`rwm_gym.resources.model_file`)."""
        return model_file(self.model, self.model_dir, self.name)

    @cached_property
    def state_columns(self) -> tuple[str, ...]:
        return tuple(f"{g.name}/{c}" for g in self.state for c in g.columns)

    @property
    def state_dim(self) -> int:
        return sum(g.size for g in self.state)

    @property
    def action_dim(self) -> int:
        return len(self.actuator.joints)

    @cached_property
    def state_slices(self) -> dict[str, slice]:
        """Slice of each state group in the state vector."""
        out, start = {}, 0
        for g in self.state:
            out[g.name] = slice(start, start + g.size)
            start += g.size
        return out

    @cached_property
    def state_mean(self) -> np.ndarray:
        return np.concatenate([np.asarray(g.mean, dtype=np.float64) for g in self.state])

    @cached_property
    def state_std(self) -> np.ndarray:
        return np.concatenate([np.asarray(g.std, dtype=np.float64) for g in self.state])

    @property
    def contact_dim(self) -> int:
        return len(self.privileged.contact_bodies)

    @property
    def foot_dim(self) -> int:
        return len(self.privileged.feet)

    @cached_property
    def observation_dim(self) -> int:
        sizes = {g.name: g.size for g in self.state}
        sizes["command"] = len(self.command.names)
        sizes["last_action"] = self.action_dim
        return sum(sizes[name] for name in self.observation.groups)


def _group(table: dict, joints: tuple[str, ...], where: str) -> Group:
    columns = joints if table["columns"] == "joints" else tuple(table["columns"])
    n = len(columns)

    def per_column(key: str) -> tuple[float, ...]:
        value = table[key]
        values = (float(value),) * n if isinstance(value, (int, float)) else tuple(float(v) for v in value)
        if len(values) != n:
            raise ValueError(f"{where}: state group {table['name']!r} has {n} columns but {len(values)} {key} values")
        return values

    return Group(table["name"], tuple(columns), table.get("unit", ""), per_column("mean"), per_column("std"))


def _symmetry(table: dict | None, joints: tuple[str, ...], where: str) -> SymmetrySpec | None:
    if table is None:
        return None
    unknown = sorted(set(table) - {"joints", "joint_signs", "signs"})
    if unknown:
        raise ValueError(f"{where}: [symmetry] unknown field {unknown[0]!r}")
    mirror = tuple(table["joints"])
    signs = tuple(float(v) for v in table["joint_signs"])
    groups = {k: tuple(float(v) for v in values) for k, values in table.get("signs", {}).items()}
    if len(mirror) != len(joints) or len(signs) != len(joints):
        raise ValueError(
            f"{where}: [symmetry] joints and joint_signs need one entry per actuated joint "
            f"({len(joints)}), got {len(mirror)} and {len(signs)}"
        )
    if stray := sorted(set(mirror) - set(joints)):
        raise ValueError(f"{where}: [symmetry] joint {stray[0]!r} is not an actuated joint")
    if any(v not in (1.0, -1.0) for values in (signs, *groups.values()) for v in values):
        raise ValueError(f"{where}: [symmetry] signs must be 1 or -1")
    return SymmetrySpec(mirror, signs, groups)


def _base_height_target(reward: dict, state: list[dict], where: str) -> float:
    """`[reward] base_height_target` (m), required with a non-zero `base_height` weight, which also needs a
    `base_height` state group; NaN where absent."""
    if not reward.get("weights", {}).get("base_height"):
        return float(reward.get("base_height_target", "nan"))
    if "base_height_target" not in reward or not any(g.get("name") == "base_height" for g in state):
        raise ValueError(
            f"{where}: reward weight base_height needs [reward] base_height_target (m) and a state group 'base_height'"
        )
    return float(reward["base_height_target"])


def parse_spec(text: str, where: str = "<spec>", model_dir: str | Path | None = None) -> TaskSpec:
    """Parse a spec from TOML text; `where` names its origin in error messages; `model_dir`: a folder the user vouches
    for, where `model` may lie besides the package's assets (the spec file's own folder; None for embedded specs)."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{where}: not valid TOML ({err})") from None
    except RecursionError:  # arrays or tables nested thousands deep
        raise ValueError(f"{where}: not valid TOML (nested too deep)") from None
    try:
        task, act = raw["task"], raw["actuator"]
        joints = tuple(act["joints"])
        # Only `joints` is required: tasks whose actions drive the simulator's own actuators (dm_control) have no
        # PD figures, and get neutral ones (zero pose, unit scale, no gains, no limits).
        actuator = ActuatorSpec(
            joints=joints,
            default_pose=tuple(float(v) for v in act.get("default_pose", [0.0] * len(joints))),
            action_scale=float(act.get("action_scale", 1.0)),
            kp=_figure(act, "kp", 0.0, len(joints), where),
            kd=_figure(act, "kd", 0.0, len(joints), where),
            effort_limit=_figure(act, "effort_limit", float("inf"), len(joints), where),
            velocity_limit=_figure(act, "velocity_limit", float("inf"), len(joints), where),
        )
        if len(actuator.default_pose) != len(joints):
            raise ValueError(
                f"{where}: actuator.default_pose has {len(actuator.default_pose)} values for {len(joints)} joints"
            )
        # [privileged], [command] and [reward] may be left out (no contacts, no commands, the simulator's reward);
        # a table that is there gives its task's numbers (no robot's values stand in as defaults here).
        priv = raw.get("privileged", {})
        cmd = raw.get("command", {})
        rew = raw.get("reward", {})
        obs = raw["observation"]
        reset = {k: float(v) for k, v in raw.get("reset", {}).items()}
        known = {"reset", "task", "actuator", "state", "privileged", "command", "reward", "observation", "symmetry"}
        return TaskSpec(
            name=task["name"],
            physics_env_id=task["physics_env_id"],
            imagined_env_id=task["imagined_env_id"],
            model=task.get("model", ""),
            policy_dt=float(task["policy_dt"]),
            physics_dt=float(task["physics_dt"]),
            episode_steps=int(task["episode_steps"]),
            keyframe=task.get("keyframe", ""),
            default_checkpoint=task.get("default_checkpoint", ""),
            base_body=task.get("base_body", ""),
            actuator=actuator,
            state=tuple(_group(g, joints, where) for g in raw["state"]),
            privileged=PrivilegedSpec(
                contact_bodies=tuple(priv.get("contact_bodies", ())),
                contact_threshold=float(priv.get("contact_threshold", 0.0)),
                feet=tuple(priv.get("feet", ())),
                thighs=tuple(priv.get("thighs", ())),
                termination_bodies=tuple(priv.get("termination_bodies", ())),
                foot_height_std=float(
                    priv["foot_height_std"] if priv.get("feet") else priv.get("foot_height_std", 1.0)
                ),
            ),
            observation=ObservationSpec(tuple(obs["groups"]), {k: float(v) for k, v in obs.get("noise", {}).items()}),
            command=CommandSpec(
                names=tuple(cmd.get("names", ())),
                low=tuple(float(v) for v in cmd.get("low", ())),
                high=tuple(float(v) for v in cmd.get("high", ())),
                resample_seconds=float(cmd.get("resample_seconds", "inf")),
                standing_fraction=float(cmd.get("standing_fraction", 0.0)),
                standing_threshold=float(cmd["standing_threshold"] if cmd.get("names") else "nan"),
            ),
            reward=RewardSpec(
                weights={k: float(v) for k, v in rew.get("weights", {}).items()},
                tracking_sigma=float(rew["tracking_sigma"] if rew.get("weights") else "nan"),
                feet_air_time_target=float(rew["feet_air_time_target"] if rew.get("weights") else "nan"),
                base_height_target=_base_height_target(rew, raw["state"], where),
            ),
            reset=ResetSpec(**reset),
            symmetry=_symmetry(raw.get("symmetry"), joints, where),
            text=text,
            extra={k: v for k, v in raw.items() if k not in known},
            model_dir=None if model_dir is None else Path(model_dir),
        )
    except KeyError as err:
        raise ValueError(f"{where}: missing field {err.args[0]!r}") from None


def load_spec(name_or_path: str | Path) -> TaskSpec:
    """Load a spec by file path or by name of a shipped spec (`"anymal_d"` -> `envs/anymal_d.toml`)."""
    path = Path(name_or_path)
    if not path.suffix:
        path = specs_dir() / f"{name_or_path}.toml"
    if not path.is_file():
        available = sorted(p.stem for p in specs_dir().glob("*.toml"))
        raise FileNotFoundError(f"task spec {str(name_or_path)!r} not found (shipped specs: {', '.join(available)})")
    own = path.parent.resolve() == specs_dir().resolve()  # a shipped spec names shipped models only
    return parse_spec(path.read_text(), where=str(path), model_dir=None if own else path.parent)


def shipped_spec(env_id: str) -> TaskSpec | None:
    """The shipped spec (`envs/*.toml`) whose physics or imagined env id is `env_id`; None if none."""
    found = shipped_spec_file(env_id)
    return None if found is None else found[1]


def shipped_spec_file(env_id: str) -> tuple[Path, TaskSpec] | None:
    """The shipped spec file whose physics or imagined env id is `env_id`, and its spec; None if none."""
    for path in sorted(specs_dir().glob("*.toml")):
        spec = parse_spec(path.read_text(), where=str(path))
        if env_id in (spec.physics_env_id, spec.imagined_env_id):
            return path, spec
    return None
