"""The shipped ANYmal D model: names and order, mass, actuators, and that it stands on its contact sensors."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np
import pytest

from rwm_gym.resources import assets_dir

LEGS = ("LF", "RF", "LH", "RH")
JOINTS = [f"{leg}_{j}" for leg in LEGS for j in ("HAA", "HFE", "KFE")]
DEFAULT_POSE_RAD = [0.0, 0.4, -0.8, 0.0, 0.4, -0.8, 0.0, -0.4, 0.8, 0.0, -0.4, 0.8]
URDF_MASS_KG = 57.1244  # sum of every <mass> in ANYbotics' anymal.urdf (d5bf4dc), when the file is not at hand
REPO = Path(__file__).resolve().parents[1]
URDF_CANDIDATES = (
    Path("/work/shared/reference/anymal_d/anymal.urdf"),
    REPO.parent / "shared" / "reference" / "anymal_d" / "anymal.urdf",
)


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(assets_dir() / "anymal_d" / "scene.xml"))


def _sensor(model: mujoco.MjModel, data: mujoco.MjData, name: str) -> float:
    sensor = model.sensor(name)
    assert sensor.dim[0] == 1, name
    return float(data.sensordata[sensor.adr[0]])


def test_bodies_joints_and_order(model: mujoco.MjModel) -> None:
    assert model.nq == 19 and model.nv == 18
    assert model.joint(0).name == "base" and model.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE
    hinges = [j for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    assert [model.joint(j).name for j in hinges] == JOINTS
    assert [int(model.jnt_qposadr[j]) for j in hinges] == list(range(7, 19))
    for leg in LEGS:
        for part in ("HIP", "THIGH", "SHANK"):
            assert model.body(f"{leg}_{part}").id > 0
        foot = model.geom(f"{leg}_FOOT")
        assert foot.type[0] == mujoco.mjtGeom.mjGEOM_SPHERE
        assert model.body(int(foot.bodyid[0])).name == f"{leg}_SHANK"
        assert foot.friction[0] == pytest.approx(1.0) and foot.condim[0] == 3
        np.testing.assert_allclose(model.site(f"{leg}_FOOT").pos, foot.pos)
    assert model.body(int(model.site("imu").bodyid[0])).name == "base"
    np.testing.assert_allclose(model.site("imu").pos, 0.0)
    assert model.opt.timestep == pytest.approx(0.005)


def test_actuators(model: mujoco.MjModel) -> None:
    assert model.nu == 12
    assert [model.actuator(a).name for a in range(model.nu)] == JOINTS
    for a in range(model.nu):
        assert model.joint(int(model.actuator_trnid[a, 0])).name == JOINTS[a]
    np.testing.assert_allclose(model.actuator_forcerange, np.tile([-80.0, 80.0], (12, 1)))
    assert model.actuator_forcelimited.all()
    # the bare model carries the task's gains, so it stands as the env (which sets them from the spec) does
    from rwm_gym.spec import load_spec

    act = load_spec("anymal_d").actuator
    np.testing.assert_allclose(model.actuator_gainprm[:, 0], act.kp)
    np.testing.assert_allclose(model.actuator_biasprm[:, 1:3], np.tile([-act.kp, -act.kd], (12, 1)))


def test_total_mass(model: mujoco.MjModel) -> None:
    reference = URDF_MASS_KG
    urdf = next((p for p in URDF_CANDIDATES if p.is_file()), None)
    if urdf is not None:  # links present in the file (a commented-out hatch, 0.097 kg, is not counted)
        reference = sum(float(i.find("mass").get("value")) for i in ET.parse(urdf).getroot().iter("inertial"))
    assert model.body_subtreemass[0] == pytest.approx(reference, rel=0.02)


def test_keyframe_feet_just_touch(model: mujoco.MjModel) -> None:
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("standing").id)
    np.testing.assert_allclose(data.qpos[7:], DEFAULT_POSE_RAD)
    np.testing.assert_allclose(data.ctrl, DEFAULT_POSE_RAD)
    mujoco.mj_kinematics(model, data)
    bottoms = [data.geom_xpos[model.geom(f"{leg}_FOOT").id][2] - model.geom(f"{leg}_FOOT").size[0] for leg in LEGS]
    assert min(bottoms) == pytest.approx(0.0, abs=1e-3)


def test_stands_on_its_feet(model: mujoco.MjModel) -> None:
    """Default pose held by the model's PD servos for 2 s: the feet carry the weight, nothing else touches."""
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("standing").id)
    for _ in range(int(2.0 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    weight = model.body_subtreemass[0] * -model.opt.gravity[2]
    feet = sum(_sensor(model, data, f"contact_{leg}_FOOT") for leg in LEGS)
    assert data.qpos[2] > 0.35
    assert feet == pytest.approx(weight, rel=0.15)
    assert _sensor(model, data, "contact_base") == 0.0
    for leg in LEGS:
        assert _sensor(model, data, f"contact_{leg}_THIGH") == 0.0


def test_contact_sensors_read_zero_in_the_air(model: mujoco.MjModel) -> None:
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("standing").id)
    data.qpos[2] += 1.0
    for _ in range(10):
        mujoco.mj_step(model, data)
    assert data.ncon == 0
    np.testing.assert_array_equal(data.sensordata, 0.0)
