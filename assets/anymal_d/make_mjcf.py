"""Regenerate `anymal_d.xml` from ANYbotics' ANYmal D URDF (developer tool, not used at run time).

Needs the reference file `shared/reference/anymal_d/anymal.urdf` (ANYbotics/anymal_d_simple_description, commit
d5bf4dc, BSD-3-Clause), which is not shipped with rwm-gym; pass its path as the first argument:

    python assets/anymal_d/make_mjcf.py /work/shared/reference/anymal_d/anymal.urdf

What it does:
- keeps 13 moving bodies: `base` (free) and per leg the children of the HAA, HFE and KFE joints (`L_HIP`,
  `L_THIGH`, `L_SHANK`); every other link is welded to its nearest moving ancestor. The inspection payload's
  pan/tilt joints are welded at 0 rad.
- lumps the welded links' masses, centres of mass and inertias (rotation into the body frame plus the
  parallel-axis theorem) into one `<inertial>` per body.
- writes every body frame aligned with the base frame at the zero pose (the URDF's 90-degree frame twists are
  folded into the joint axes), so positions and axes read directly in base coordinates.
- keeps the URDF's collision primitives as geoms (boxes, spheres; cylinders become capsules on the same axis segment
  and radius, cheaper to collide); the sphere of each foot link becomes the `L_FOOT` geom on the shank.
Numbers are rounded: lengths to 0.01 mm, masses to 0.01 g, inertias to 1e-7 kg·m².
"""

from __future__ import annotations

import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

LEGS = ("LF", "RF", "LH", "RH")
LEG_JOINTS = ("HAA", "HFE", "KFE")
BODY_OF_JOINT = {"HAA": "HIP", "HFE": "THIGH", "KFE": "SHANK"}
DEFAULT_POSE_RAD = {"LF": (0.0, 0.4, -0.8), "RF": (0.0, 0.4, -0.8), "LH": (0.0, -0.4, 0.8), "RH": (0.0, -0.4, 0.8)}
HERE = Path(__file__).resolve().parent


def _vec(text: str | None) -> np.ndarray:
    return np.array([float(v) for v in (text or "0 0 0").split()])


def _rpy(rpy: np.ndarray) -> np.ndarray:
    """URDF fixed-axis roll-pitch-yaw to a rotation matrix R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


def _origin(elem: ET.Element | None) -> tuple[np.ndarray, np.ndarray]:
    """(R, p) of an URDF <origin> element (identity when absent)."""
    o = None if elem is None else elem.find("origin")
    if o is None:
        return np.eye(3), np.zeros(3)
    return _rpy(_vec(o.get("rpy"))), _vec(o.get("xyz"))


@dataclass(frozen=True)
class Geom:
    """A collision primitive in its body's (base-aligned) frame; lengths in m."""

    kind: str  # "box" | "cylinder" | "sphere"
    pos: np.ndarray  # centre
    size: np.ndarray  # box half-sizes, or (radius,)
    axis: np.ndarray | None = None  # cylinder half-length vector along its axis

    def attrs(self) -> str:
        if self.kind == "cylinder":
            # A capsule on the cylinder's axis segment and radius: capsule-plane contacts are analytic and
            # cheaper, and these shapes touch the floor only when the robot kneels or falls.
            ends = f"{_fv(self.pos - self.axis)}  {_fv(self.pos + self.axis)}"
            return f'type="capsule" fromto="{ends}" size="{_fv(self.size, 6)}"'
        return f'type="{self.kind}" pos="{_fv(self.pos)}" size="{_fv(self.size, 6)}"'

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        ext = (
            self.size
            if self.kind == "box"
            else np.full(3, self.size[0]) + (np.abs(self.axis) if self.axis is not None else 0.0)
        )
        return self.pos - ext, self.pos + ext


@dataclass
class Body:
    """A moving MuJoCo body: origin in the base frame at the zero pose, its joint and what was lumped into it."""

    name: str
    origin: np.ndarray
    parent: str | None = None
    axis: np.ndarray | None = None
    joint_range: tuple[float, float] | None = None
    masses: list[tuple[float, np.ndarray, np.ndarray]] = field(default_factory=list)  # (kg, com, I about com)
    geoms: list[Geom] = field(default_factory=list)


def _fmt(x: float, nd: int = 5) -> str:
    s = f"{round(float(x), nd):.{nd}f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _fv(v: np.ndarray, nd: int = 5) -> str:
    return " ".join(_fmt(x, nd) for x in v)


def parse(urdf: Path) -> dict[str, Body]:
    """Walk the URDF tree from `base` and lump every link into its moving body, keyed by body name."""
    root = ET.parse(urdf).getroot()
    links = {link.get("name"): link for link in root.findall("link")}
    children: dict[str, list[ET.Element]] = {}
    for j in root.findall("joint"):
        children.setdefault(j.find("parent").get("link"), []).append(j)
    leg_joints = {f"{leg}_{j}" for leg in LEGS for j in LEG_JOINTS}
    bodies = {"base": Body("base", np.zeros(3))}

    def visit(link: str, rot: np.ndarray, pos: np.ndarray, body: Body) -> None:
        elem = links[link]
        inertial = elem.find("inertial")
        if inertial is not None:
            ro, po = _origin(inertial)
            i = inertial.find("inertia")
            ixx, iyy, izz, ixy, ixz, iyz = (float(i.get(k)) for k in ("ixx", "iyy", "izz", "ixy", "ixz", "iyz"))
            r = rot @ ro
            local = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
            body.masses.append((float(inertial.find("mass").get("value")), pos + rot @ po, r @ local @ r.T))
        for col in elem.findall("collision"):
            rc, pc = _origin(col)
            body.geoms.append(_geom(col.find("geometry")[0], rot @ rc, pos + rot @ pc - body.origin, link))
        for j in children.get(link, []):
            rj, pj = _origin(j)
            child, crot, cpos = j.find("child").get("link"), rot @ rj, pos + rot @ pj
            if j.get("name") not in leg_joints:  # fixed, or a payload joint welded at 0 rad
                visit(child, crot, cpos, body)
                continue
            lim = j.find("limit")
            bodies[child] = Body(
                child,
                cpos,
                body.name,
                crot @ _vec(j.find("axis").get("xyz")),
                (float(lim.get("lower")), float(lim.get("upper"))),
            )
            visit(child, crot, cpos, bodies[child])

    visit("base", np.eye(3), np.zeros(3), bodies["base"])
    expected = {"base"} | {f"{leg}_{b}" for leg in LEGS for b in BODY_OF_JOINT.values()}
    if set(bodies) != expected:
        raise ValueError(f"{urdf}: moving links {sorted(bodies)} differ from {sorted(expected)}")
    return bodies


def _geom(g: ET.Element, r: np.ndarray, c: np.ndarray, link: str) -> Geom:
    """One URDF collision primitive in the (base-aligned) body frame."""
    if g.tag == "box":
        if not np.allclose(np.abs(r), np.round(np.abs(r)), atol=1e-9):
            raise ValueError(f"{link}: box not axis-aligned in the body frame")
        return Geom("box", c, np.abs(r) @ (_vec(g.get("size")) / 2))
    radius = np.array([float(g.get("radius"))])
    if g.tag == "cylinder":
        return Geom("cylinder", c, radius, r[:, 2] * float(g.get("length")) / 2)
    if g.tag == "sphere":
        return Geom("sphere", c, radius)
    raise ValueError(f"{link}: unsupported collision geometry {g.tag}")


def lump(b: Body) -> tuple[float, np.ndarray, np.ndarray]:
    """Total mass (kg), centre of mass in the body frame (m) and inertia about it (kg·m², parallel-axis theorem)."""
    m = sum(mi for mi, _, _ in b.masses)
    com = sum(mi * ci for mi, ci, _ in b.masses) / m
    inertia = np.zeros((3, 3))
    for mi, ci, ii in b.masses:
        d = ci - com
        inertia += ii + mi * (d @ d * np.eye(3) - np.outer(d, d))
    return m, com - b.origin, inertia


def _touch_box(name: str, geoms: list[Geom], margin: float) -> str:
    """A box site enclosing `geoms` (plus margin): the volume of a touch sensor."""
    lo = np.min([g.bounds()[0] for g in geoms], axis=0) - margin
    hi = np.max([g.bounds()[1] for g in geoms], axis=0) + margin
    return f'<site name="{name}" class="touch" type="box" pos="{_fv((lo + hi) / 2)}" size="{_fv((hi - lo) / 2)}"/>'


def _inertial(b: Body) -> str:
    m, com, i = lump(b)
    full = [i[0, 0], i[1, 1], i[2, 2], i[0, 1], i[0, 2], i[1, 2]]
    return f'<inertial pos="{_fv(com)}" mass="{_fmt(m)}" fullinertia="{_fv(full, 7)}"/>'


def _leg(bodies: dict[str, Body], leg: str) -> list[str]:
    hip, thigh, shank = (bodies[f"{leg}_{n}"] for n in ("HIP", "THIGH", "SHANK"))
    out = [f"<!-- ===== {leg} leg ===== -->"]
    for depth, (b, joint) in enumerate(zip((hip, thigh, shank), LEG_JOINTS)):
        ind = "  " * depth
        lo, hi = b.joint_range
        rng = f'range="{_fmt(lo, 6)} {_fmt(hi, 6)}"'
        out += [
            f'{ind}<body name="{b.name}" pos="{_fv(b.origin - bodies[b.parent].origin)}">',
            f'{ind}  <joint name="{leg}_{joint}" axis="{_fv(b.axis, 6)}" {rng}/>',
            f"{ind}  {_inertial(b)}",
        ]
        if b is hip:
            hfe = thigh.origin - hip.origin
            out += [
                f"{ind}  <!-- The URDF has no collision primitive on the hip: visual only. -->",
                f'{ind}  <geom class="visual" type="capsule" fromto="0 0 0  {_fv(hfe)}" size="0.045"/>',
            ]
        elif b is thigh:
            out += [f"{ind}  <!-- HFE drive housing, thigh end caps and tube, KFE drive housing. -->"]
            out += [f'{ind}  <geom name="{b.name}_{n}" class="leg" {g.attrs()}/>' for n, g in enumerate(b.geoms)]
            out += [f"{ind}  {_touch_box(f'contact_{b.name}', b.geoms, 0.01)}"]
        else:
            feet = [g for g in b.geoms if g.kind == "sphere"]
            if len(feet) != 1:
                raise ValueError(f"{b.name}: expected one foot sphere, found {len(feet)}")
            foot = feet[0]
            out += [f"{ind}  <!-- Knee housing, shank and foot tube; the foot sphere of the welded URDF foot link. -->"]
            out += [
                f'{ind}  <geom name="{b.name}_{n}" class="leg" {g.attrs()}/>'
                for n, g in enumerate(g for g in b.geoms if g is not foot)
            ]
            out += [
                f'{ind}  <geom name="{leg}_FOOT" class="foot" pos="{_fv(foot.pos)}" size="{_fv(foot.size, 6)}"/>',
                f'{ind}  <site name="{leg}_FOOT" class="touch" type="sphere" pos="{_fv(foot.pos)}" '
                f'size="{_fmt(foot.size[0] * 1.1)}"/>',
            ]
    out += ["  " * d + "</body>" for d in (2, 1, 0)]
    return out


def render(bodies: dict[str, Body], base_z: float) -> str:
    """The MJCF text of the robot (see TEMPLATE)."""
    base = bodies["base"]
    lines = [
        _inertial(base),
        '<site name="imu" pos="0 0 0" size="0.01"/>',
        _touch_box("contact_base", base.geoms, 0.02),
        "<!-- Main body box, the four HAA drive housings, lidar, payload mount and payload head. -->",
    ]
    lines += [f'<geom name="base_{n}" class="body" {g.attrs()}/>' for n, g in enumerate(base.geoms)]
    for leg in LEGS:
        lines += ["", *_leg(bodies, leg)]
    body_text = "\n".join(("      " + s) if s else "" for s in lines)
    pose = " ".join(_fmt(v) for leg in LEGS for v in DEFAULT_POSE_RAD[leg])
    mass = sum(m for b in bodies.values() for m, _, _ in b.masses)
    actuators = "\n".join(f'    <position name="{j}" class="anymal" joint="{j}"/>' for j in JOINT_NAMES)
    thighs = "\n".join(f'    <touch name="contact_{leg}_THIGH" site="contact_{leg}_THIGH"/>' for leg in LEGS)
    feet = "\n".join(f'    <touch name="contact_{leg}_FOOT" site="{leg}_FOOT"/>' for leg in LEGS)
    return TEMPLATE.format(
        bodies=body_text,
        base_z=_fmt(base_z, 4),
        pose=pose,
        urdf_mass=_fmt(mass, 4),
        actuators=actuators,
        thighs=thighs,
        feet=feet,
    )


def standing_height(xml: str) -> float:
    """Base height (m) at which the lowest foot sphere touches z = 0 in the default pose."""
    import mujoco

    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    data.qpos[2] = 0.0
    data.qpos[7:] = [v for leg in LEGS for v in DEFAULT_POSE_RAD[leg]]
    mujoco.mj_kinematics(model, data)
    feet = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"{leg}_FOOT") for leg in LEGS]
    return float(-min(data.geom_xpos[g][2] - model.geom_size[g][0] for g in feet))


JOINT_NAMES = [f"{leg}_{j}" for leg in LEGS for j in LEG_JOINTS]

TEMPLATE = """<!--
  ANYmal D (ANYbotics) for rwm-gym.
  Figures (masses, inertias, joint frames, axes, limits, collision primitives) from ANYbotics'
  anymal_d_simple_description, commit d5bf4dc, BSD-3-Clause: see LICENSE and README.md in this folder.
  Generated by make_mjcf.py; fixed URDF links are lumped into 13 moving bodies. Every body frame is
  parallel to the base frame at the zero pose (x forward, y left, z up). Total mass {urdf_mass} kg.
-->
<mujoco model="anymal_d">
  <compiler angle="radian" autolimits="true"/>
  <!-- Solver settings of legged-RL MuJoCo models (MuJoCo Playground's quadrupeds): a pyramidal friction
       cone and a few Newton and line-search iterations; two no-slip iterations make static friction hold
       (without them the feet, 0.2 m outboard of the HAA axes, creep outward and the standing base sinks
       by about 1 cm/s). benchmarks/physics.py times this against the previous elliptic cone, impratio 100
       and 100 solver iterations, which stood and walked the same but stepped about 2x slower. -->
  <option timestep="0.005" integrator="implicitfast" cone="pyramidal" iterations="4" ls_iterations="8"
          noslip_iterations="2"/>

  <default>
    <default class="anymal">
      <!-- Damping and friction loss are 0: the sim-to-real workflow adds them as hidden effects.
           Armature 0: no reflected rotor inertia is published with the URDF. -->
      <joint damping="0" frictionloss="0" armature="0"/>
      <!-- Robot geoms (contype 2, conaffinity 1) touch the floor (contype 1) but never each other. -->
      <geom contype="2" conaffinity="1" condim="3" friction="1 0.005 0.0001" solref="0.02 1"
            solimp="0.9 0.95 0.001 0.5 2"/>
      <!-- PD gains and torque limit (N·m/rad, N·m·s/rad, N·m) of envs/anymal_d.toml, so the bare model stands
           as the env does; the env sets them from the spec (and PhysicsParams) when it loads the model. -->
      <position kp="80" kv="2" forcelimited="true" forcerange="-80 80" ctrllimited="false"/>
      <site group="4" rgba="0.9 0.2 0.2 0.3"/>
      <default class="body">
        <geom rgba="0.75 0.75 0.75 1"/>
      </default>
      <default class="leg">
        <geom rgba="0.85 0.35 0.1 1"/>
      </default>
      <default class="foot">
        <geom type="sphere" friction="1 0.005 0.0001" rgba="0.15 0.15 0.15 1"/>
      </default>
      <default class="visual">
        <geom contype="0" conaffinity="0" group="1" rgba="0.3 0.3 0.3 1"/>
      </default>
      <!-- Touch-sensor volumes: each sums the normal force of its body's contacts inside it. -->
      <default class="touch">
        <site group="4"/>
      </default>
    </default>
  </default>

  <worldbody>
    <body name="base" pos="0 0 {base_z}" childclass="anymal">
      <freejoint name="base"/>
      <!-- Lumped into the base: base, shells, faces, cameras, battery, docking socket, HBC receiver,
           lidar, the four HAA drives and the inspection payload (pan/tilt welded at 0 rad). -->
{bodies}
    </body>
  </worldbody>

  <!-- One PD position servo per joint, leg-major LF, RF, LH, RH x HAA, HFE, KFE. class="anymal" is
       needed: actuators do not inherit the base body's childclass. -->
  <actuator>
{actuators}
  </actuator>

  <!-- Contact sensors (N): normal contact force summed over the body's contacts (touch sensors). -->
  <sensor>
    <touch name="contact_base" site="contact_base"/>
{thighs}
{feet}
  </sensor>

  <!-- Default pose (rad); base height puts the feet just on the floor. -->
  <keyframe>
    <key name="standing" qpos="0 0 {base_z} 1 0 0 0 {pose}" ctrl="{pose}"/>
  </keyframe>
</mujoco>
"""


def main(urdf: Path) -> None:
    bodies = parse(urdf)
    base_z = standing_height(render(bodies, 0.0))
    (HERE / "anymal_d.xml").write_text(render(bodies, base_z))
    mass = sum(m for b in bodies.values() for m, _, _ in b.masses)
    print(f"wrote {HERE / 'anymal_d.xml'}: {mass:.4f} kg, standing base height {base_z:.4f} m")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python make_mjcf.py PATH/TO/anymal.urdf")
    main(Path(sys.argv[1]))
