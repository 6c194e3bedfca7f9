"""A signed payload: a negative `payload_mass` is a robot lighter than its model (mass the base body lacks), built by
the physics, hidden by make-measured and found by the gap fit."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from rwm_gym.cli import main
from rwm_gym.data.dataset import Dataset
from rwm_gym.gap.correct import write_corrected
from rwm_gym.gap.effects import vocabulary
from rwm_gym.gap.fit import fit_all
from rwm_gym.gap.measured import SensorNoise, make_measured
from rwm_gym.physics.params import MAX_REMOVED_SHARE, PhysicsParams, build_model
from rwm_gym.spec import load_spec
from tests.test_gap_effects import _fit_inputs

SPEC = load_spec("anymal_d")
LIGHTER_KG = 5.7
"""About a tenth of ANYmal D's 57 kg."""


def _weight_on_the_ground(model: mujoco.MjModel) -> float:
    """Sum of the floor's normal contact forces (N) once the robot stands still at its default pose."""
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    data.ctrl[:] = data.qpos[7:]
    mujoco.mj_step(model, data, 1500)
    force = np.zeros(6)
    total = 0.0
    for i in range(data.ncon):
        mujoco.mj_contactForce(model, data, i, force)
        total += force[0]
    return total


def test_a_negative_payload_makes_the_base_lighter_by_that_much():
    nominal = build_model(SPEC)
    light = build_model(SPEC, params=PhysicsParams(payload_mass=-LIGHTER_KG, payload_com=(0.1, 0.0, 0.0)))
    base = nominal.body(SPEC.base_body).id
    assert light.nbody == nominal.nbody  # no body added: the base's own figures change
    assert light.body_mass[base] == pytest.approx(nominal.body_mass[base] - LIGHTER_KG)
    assert mujoco.mj_getTotalmass(light) == pytest.approx(mujoco.mj_getTotalmass(nominal) - LIGHTER_KG)
    left = light.body_mass[base] / nominal.body_mass[base]
    np.testing.assert_allclose(light.body_inertia[base], left * nominal.body_inertia[base], rtol=1e-9)
    # the centre of mass moves away from where the mass was taken: the inverse of a payload added there
    moved = (nominal.body_mass[base] * nominal.body_ipos[base] - LIGHTER_KG * np.array([0.1, 0, 0])) / light.body_mass[
        base
    ]
    np.testing.assert_allclose(light.body_ipos[base], moved, atol=1e-9)
    g = -nominal.opt.gravity[2]
    assert _weight_on_the_ground(nominal) - _weight_on_the_ground(light) == pytest.approx(LIGHTER_KG * g, rel=0.02)


def test_a_payload_that_takes_more_than_the_rule_allows_is_refused_in_one_line():
    base = build_model(SPEC).body(SPEC.base_body).mass[0]
    lowest = -MAX_REMOVED_SHARE * base
    assert vocabulary(SPEC)["payload"].parameters[0].low == pytest.approx(lowest)
    build_model(SPEC, params=PhysicsParams(payload_mass=0.99 * lowest))
    with pytest.raises(ValueError, match=r"^physics parameter 'payload_mass' .* takes more than 50% of the base") as e:
        build_model(SPEC, params=PhysicsParams(payload_mass=1.01 * lowest))
    assert "\n" not in str(e.value)


def test_the_corrected_mjcf_holds_a_lighter_robot(tmp_path):
    params = PhysicsParams(payload_mass=-LIGHTER_KG, payload_com=(-0.1, 0.05, 0.0))
    written = mujoco.MjModel.from_xml_path(write_corrected(SPEC, params, tmp_path)["mjcf"])
    direct = build_model(SPEC, params=params)
    base = direct.body(SPEC.base_body).id
    for name in ("body_mass", "body_inertia", "body_ipos"):
        np.testing.assert_allclose(getattr(written, name)[base], getattr(direct, name)[base], rtol=1e-5, err_msg=name)


def test_make_measured_hides_a_lighter_robot_and_refuses_an_impossible_one(tmp_path, capsys):
    def make(magnitude: str, out) -> int:
        return main(
            [
                "make-measured",
                "--effect",
                "payload",
                magnitude,
                "--episodes",
                "1",
                "--max-steps",
                "5",
                "--out",
                str(out),
            ]
        )

    out = tmp_path / "light.h5"
    assert make(f"--magnitude=-{LIGHTER_KG},0.1", out) == 0
    assert "(hidden: payload)" in capsys.readouterr().out and Dataset.load(out).num_episodes == 1
    refused = tmp_path / "sub" / "heavy.h5"
    assert make("--magnitude=-30", refused) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "payload_mass" in err and "base body" in err, err
    assert not refused.parent.exists()  # refused before anything is written


def test_the_fit_finds_a_lighter_robots_sign_and_magnitude(tmp_path):
    """A robot 5.7 kg lighter than its model in 4 x 100 steps of noise-free excitation data: the payload's fit
    searches below zero and lands on the hidden mass (with the default sensor noise the benchmark's lighter rows
    measure it: docs/results/gap-workflow.md)."""
    effect = vocabulary(SPEC)["payload"]
    path = make_measured(
        {"payload": effect.values_from_magnitude(-LIGHTER_KG)},
        4,
        tmp_path / "m.h5",
        max_steps=100,
        noise=SensorNoise(scale=0.0),
        progress=False,
    )
    inputs = _fit_inputs(path)
    (fit,) = fit_all({"payload": effect}, inputs, progress=False)
    assert fit.values[0] == pytest.approx(-LIGHTER_KG, rel=0.05), fit.values
    assert fit.gap_mean < 0.01 * float(inputs.before.mean())
