"""The robot's left-right mirror as index and sign arrays, read from the spec's `[symmetry]` table.

A left-right symmetric robot that tracks a command does, in the mirror, the mirror image of what it does: a
mirrored sample is as good a training sample as the one it came from. `Mirror` maps a vector laid out one way (the
policy observation, the action, the world-model state) to its mirror image: `x[..., index] * sign`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rwm_gym.spec import SymmetrySpec, TaskSpec, shipped_spec


@dataclass(frozen=True, eq=False)
class Mirror:
    """The mirror image of vectors of one layout: column i of the image is `sign[i] * x[index[i]]`."""

    index: np.ndarray
    """(D,) int, the column each column of the image is taken from."""
    sign: np.ndarray
    """(D,) float32, +1 or -1."""

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Mirror image of x (..., D)."""
        return x[..., self.index] * self.sign


def symmetry_table(spec: TaskSpec) -> SymmetrySpec:
    """The spec's `[symmetry]` table. A spec stored in an older checkpoint or dataset, written before its shipped spec
    gained the table, borrows the shipped spec's when the robot and every layout agree. ValueError when there is none.
    """
    if spec.symmetry is not None:
        return spec.symmetry
    shipped = shipped_spec(spec.physics_env_id)

    def layout(s: TaskSpec) -> tuple:
        return (s.name, s.model, s.actuator.joints, s.state_columns, s.observation.groups, s.command.names)

    if shipped is not None and shipped.symmetry is not None and layout(shipped) == layout(spec):
        return shipped.symmetry
    raise ValueError(f"task spec {spec.name} has no [symmetry] table (the robot's left-right mirror)")


def _joint_mirror(spec: TaskSpec, table: SymmetrySpec) -> Mirror:
    joints = spec.actuator.joints
    index = np.array([joints.index(name) for name in table.joints])
    mirror = Mirror(index, np.asarray(table.joint_signs, dtype=np.float32))
    if not np.array_equal(index[index], np.arange(len(joints))) or np.any(mirror.sign * mirror.sign[index] != 1):
        raise ValueError(
            f"task spec {spec.name}: [symmetry] joints are not a mirror (mirroring twice must give "
            f"every joint back with its sign)"
        )
    # actions and joint_pos are offsets from the default pose: the pose must be its own mirror image
    pose = np.asarray(spec.actuator.default_pose)
    if not np.allclose(mirror(pose), pose):
        raise ValueError(f"task spec {spec.name}: actuator.default_pose is not its own mirror image under [symmetry]")
    return mirror


def _mirror(spec: TaskSpec, groups: tuple[str, ...]) -> Mirror:
    """The mirror of vectors made of `groups` in this order (state groups, `command`, `last_action`)."""
    table = symmetry_table(spec)
    joints = _joint_mirror(spec, table)
    columns = {g.name: g.columns for g in spec.state}
    columns["command"] = spec.command.names
    columns["last_action"] = spec.actuator.joints
    index, sign, start = [], [], 0
    for name in groups:
        size = len(columns[name])
        if columns[name] == spec.actuator.joints:
            index.append(start + joints.index)
            sign.append(joints.sign)
        elif name in table.signs:
            if len(table.signs[name]) != size:
                raise ValueError(
                    f"task spec {spec.name}: [symmetry.signs] {name} has {len(table.signs[name])} "
                    f"signs for {size} columns"
                )
            index.append(start + np.arange(size))
            sign.append(np.asarray(table.signs[name], dtype=np.float32))
        else:
            raise ValueError(f"task spec {spec.name}: [symmetry.signs] has no signs for group {name!r}")
        start += size
    return Mirror(np.concatenate(index), np.concatenate(sign))


def observation_mirror(spec: TaskSpec) -> Mirror:
    """Mirror of the policy observation (`observation.groups`)."""
    return _mirror(spec, spec.observation.groups)


def action_mirror(spec: TaskSpec) -> Mirror:
    """Mirror of the action (one entry per actuated joint)."""
    return _joint_mirror(spec, symmetry_table(spec))


def state_mirror(spec: TaskSpec) -> Mirror:
    """Mirror of the world-model state (the `[[state]]` groups)."""
    return _mirror(spec, tuple(g.name for g in spec.state))


def side_tokens(spec: TaskSpec) -> dict[str, str]:
    """The name tokens that swap sides, read off the joint pairs: `FL_hip_joint` <-> `FR_hip_joint` gives FL <-> FR,
    `left_knee_joint` <-> `right_knee_joint` gives left <-> right. Names split at underscores; a pair whose names
    differ in more than one token says nothing (ValueError if no pair does)."""
    table = symmetry_table(spec)
    tokens: dict[str, str] = {}
    for joint, partner in zip(spec.actuator.joints, table.joints):
        a, b = joint.split("_"), partner.split("_")
        differ = [(x, y) for x, y in zip(a, b) if x != y] if len(a) == len(b) else []
        if len(differ) == 1:
            tokens[differ[0][0]] = differ[0][1]
            tokens[differ[0][1]] = differ[0][0]
    if not tokens:
        raise ValueError(
            f"task spec {spec.name}: no [symmetry] joint pair differs in one underscore-separated token (e.g. "
            f"FL_hip <-> FR_hip), so the mirror of a body's name is unknown"
        )
    return tokens


def name_mirror(spec: TaskSpec, names: tuple[str, ...] | list[str]) -> np.ndarray:
    """(N,) int: the position in `names` of each name's mirror image (its side tokens swapped, `side_tokens`); a name
    with no side token is its own image. ValueError when an image is not in `names`."""
    tokens = side_tokens(spec)
    names = list(names)
    index = []
    for name in names:
        image = "_".join(tokens.get(part, part) for part in name.split("_"))
        if image not in names:
            raise ValueError(f"task spec {spec.name}: body {name!r} mirrors to {image!r}, which is not beside it")
        index.append(names.index(image))
    return np.asarray(index, dtype=np.int64)


def contact_mirror(spec: TaskSpec) -> np.ndarray:
    """(C,) int: the mirror permutation of the contact flags (`privileged.contact_bodies`)."""
    return name_mirror(spec, spec.privileged.contact_bodies)


def foot_mirror(spec: TaskSpec) -> np.ndarray:
    """(F,) int: the mirror permutation of the foot heights (`privileged.feet`)."""
    return name_mirror(spec, spec.privileged.feet)
