"""Which bodies of a legged robot's MJCF are its feet, and where each foot meets the floor (`rwm-gym spec --mjcf`).

A geom collides if its contype or conaffinity is set or if an explicit `<pair>` names it (MJX-style models, such as
MuJoCo Menagerie's `unitree_g1/g1_mjx.xml`, switch every contact off and list foot-floor pairs). A geom touches the
floor if its collision bits meet a world geom's, or a pair joins it to one.

The feet are the robot's leaf bodies with a geom that touches the floor, kept where their lowest point at the default
pose is within `FOOT_LEVEL` of the lowest: a quadruped's four feet, a humanoid's two (its hands are leaves too, but
up in the air). A foot's point for heights is its lowest sphere or capsule end, or the bottom face of a box; its sole
is every colliding geom of the body within `SOLE_LEVEL` of that point (a G1's box and three capsules), which its touch
site encloses.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

_BODY = mujoco.mjtObj.mjOBJ_BODY
_SPHERE, _CAPSULE, _BOX = (int(mujoco.mjtGeom.mjGEOM_SPHERE), int(mujoco.mjtGeom.mjGEOM_CAPSULE),
                           int(mujoco.mjtGeom.mjGEOM_BOX))  # fmt: skip

FOOT_LEVEL = 0.03
"""m: a leaf body whose lowest point at the default pose is this close to the lowest leaf's stands on the floor."""
SOLE_LEVEL = 0.01
"""m: a foot's colliding geoms this close to its lowest point make its sole (enclosed by its touch site)."""


def _name(model: mujoco.MjModel, i: int) -> str:
    return mujoco.mj_id2name(model, _BODY, i) or ""


def _body_geoms(model: mujoco.MjModel, body: int) -> range:
    return range(model.body_geomadr[body], model.body_geomadr[body] + model.body_geomnum[body])


def pair_geoms(model: mujoco.MjModel) -> set[int]:
    """Geoms named by an explicit contact `<pair>`."""
    return {int(g) for g in model.pair_geom1[: model.npair]} | {int(g) for g in model.pair_geom2[: model.npair]}


def colliding_geoms(model: mujoco.MjModel, body: int) -> list[int]:
    """The body's geoms that take part in contacts: collision bits set, or named by a `<pair>`."""
    paired = pair_geoms(model)
    return [g for g in _body_geoms(model, body) if model.geom_contype[g] or model.geom_conaffinity[g] or g in paired]


def floor_geoms(model: mujoco.MjModel) -> set[int]:
    """Robot geoms (not on the world body) that can touch a world geom: by collision bits, or by a `<pair>` with one.
    A world without a plane is given one with contype 1 and conaffinity 1 (the floor the generator adds)."""
    world = [g for g in range(model.ngeom) if model.geom_bodyid[g] == 0]
    bits = [(int(model.geom_contype[w]), int(model.geom_conaffinity[w])) for w in world]
    if not any(int(model.geom_type[w]) == int(mujoco.mjtGeom.mjGEOM_PLANE) for w in world):
        bits.append((1, 1))
    out = set()
    for g in range(model.ngeom):
        if model.geom_bodyid[g] == 0:
            continue
        contype, conaffinity = int(model.geom_contype[g]), int(model.geom_conaffinity[g])
        if any(contype & w_affinity or w_type & conaffinity for w_type, w_affinity in bits):
            out.add(g)
    for g1, g2 in zip(model.pair_geom1[: model.npair], model.pair_geom2[: model.npair]):
        if model.geom_bodyid[g1] == 0 and model.geom_bodyid[g2] != 0:
            out.add(int(g2))
        elif model.geom_bodyid[g2] == 0 and model.geom_bodyid[g1] != 0:
            out.add(int(g1))
    return out


def _geom_rotation(model: mujoco.MjModel, g: int) -> np.ndarray:
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, model.geom_quat[g])
    return mat.reshape(3, 3)


def _extreme_points(model: mujoco.MjModel, g: int) -> tuple[np.ndarray, float] | None:
    """(points (K, 3) in the body frame, radius m) whose lowest, less the radius, is the geom's lowest point: a
    sphere's centre, a capsule's two ends, a box's eight corners; None for other shapes."""
    kind, size, pos = int(model.geom_type[g]), model.geom_size[g], model.geom_pos[g]
    if kind == _SPHERE:
        return pos[None].copy(), float(size[0])
    if kind == _CAPSULE:
        half = size[1] * _geom_rotation(model, g)[:, 2]
        return np.stack([pos + half, pos - half]), float(size[0])
    if kind == _BOX:
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
        return pos + (signs * size) @ _geom_rotation(model, g).T, 0.0
    return None


def lowest_z(model: mujoco.MjModel, data: mujoco.MjData, g: int) -> float:
    """m, the world height of geom g's lowest point at `data`'s pose (other shapes than sphere, capsule and box: their
    centre less their bounding radius)."""
    body = int(model.geom_bodyid[g])
    rot = data.xmat[body].reshape(3, 3)
    found = _extreme_points(model, g)
    if found is None:
        return float(data.geom_xpos[g, 2] - model.geom_rbound[g])
    points, radius = found
    return float(np.min((data.xpos[body] + points @ rot.T)[:, 2])) - radius


@dataclass(frozen=True)
class FootPoint:
    """Where a foot's height is read: the geom, a point in the body frame, and the distance from that point down to
    the geom's surface (a sphere or capsule's radius; 0 for the centre of a box's bottom face)."""

    geom: int
    point: np.ndarray
    radius: float
    sole: tuple[int, ...]
    """The body's colliding geoms within `SOLE_LEVEL` of the lowest point (the touch site encloses them)."""


def foot_point(model: mujoco.MjModel, data: mujoco.MjData, body: int) -> FootPoint:
    """The foot point of `body` at `data`'s pose: its lowest floor-touching sphere or capsule end, else the bottom face
    centre of its lowest floor-touching box."""
    touching = floor_geoms(model)
    rot = data.xmat[body].reshape(3, 3)
    best = None
    for g in [g for g in colliding_geoms(model, body) if g in touching]:
        found = _extreme_points(model, g)
        if found is None:
            continue
        points, radius = found
        heights = (data.xpos[body] + points @ rot.T)[:, 2] - radius
        z = float(heights.min())
        if int(model.geom_type[g]) == _BOX:  # the face whose outward normal points most downward
            down = rot.T @ np.array([0.0, 0.0, -1.0])
            local = _geom_rotation(model, g).T @ down
            axis = int(np.argmax(np.abs(local)))
            face = np.zeros(3)
            face[axis] = np.sign(local[axis]) * model.geom_size[g, axis]
            point = model.geom_pos[g] + _geom_rotation(model, g) @ face
        else:
            point = points[int(np.argmin(heights))]
        rank = (z, int(model.geom_type[g]) == _BOX)  # at equal height a round end beats a box face
        if best is None or rank < best[0]:
            best = (rank, g, point, radius)
    if best is None:
        raise ValueError(f"foot body {_name(model, body)!r} has no sphere, capsule or box geom that touches the floor")
    (z, _), g, point, radius = best
    sole = tuple(h for h in colliding_geoms(model, body) if lowest_z(model, data, h) <= z + SOLE_LEVEL)
    return FootPoint(g, np.asarray(point, dtype=float), radius, sole)


def sole_box(model: mujoco.MjModel, geoms: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(centre, half sizes) in the body frame of a box around the geoms' own extents (sphere, capsule, box; others by
    their bounding sphere), 10 % and 2 mm larger, so that every contact on them lies inside."""
    lows, highs = [], []
    for g in geoms:
        found = _extreme_points(model, g)
        if found is None:
            points, radius = model.geom_pos[g][None], float(model.geom_rbound[g])
        else:
            points, radius = found
        lows.append(points.min(axis=0) - radius)
        highs.append(points.max(axis=0) + radius)
    low, high = np.min(lows, axis=0), np.max(highs, axis=0)
    return (low + high) / 2, 1.1 * (high - low) / 2 + 0.002


def standing_feet(
    model: mujoco.MjModel, data: mujoco.MjData, leaves: list[int], pose: str, notes: list[str]
) -> list[int]:
    """The leaf bodies that stand on the floor at `data`'s pose: their lowest floor-touching point within
    `FOOT_LEVEL` of the lowest leaf's. `pose` names the pose in the note."""
    touching = floor_geoms(model)
    low = {b: min(lowest_z(model, data, g) for g in colliding_geoms(model, b) if g in touching) for b in leaves}
    floor = min(low.values())
    feet = [b for b in leaves if low[b] <= floor + FOOT_LEVEL]
    note = f"feet: the leaf bodies on the floor at {pose} (lowest point within {FOOT_LEVEL} m of the lowest): "
    note += ", ".join(_name(model, b) for b in feet)
    if up := [b for b in leaves if b not in feet]:
        above = ", ".join(f"{_name(model, b)} ({low[b] - floor:.2f} m up)" for b in up)
        note += f"; leaves above it, not feet: {above}"
    notes.append(note)
    return feet


def leaf_bodies(model: mujoco.MjModel, base: int, robot: list[int]) -> list[int]:
    """The robot's leaf bodies (no child) below `base` with a geom that touches the floor."""
    touching = floor_geoms(model)
    return [
        c
        for c in robot
        if c != base
        and not any(model.body_parentid[k] == c for k in robot)
        and any(g in touching for g in colliding_geoms(model, c))
    ]
