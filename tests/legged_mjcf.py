"""A small four-legged robot written as MJCF text, for the tests of `rwm-gym spec --mjcf` (motors, no sensors,
no keyframe: everything the generator must add), and a variant with per-class position servos and force ranges."""

LEG = """
      <body name="{n}_thigh" pos="{x} {y} 0">
        <joint name="{n}_hip" axis="0 1 0" range="-1 1"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.12" size="0.015" mass="0.1"/>
        <body name="{n}_shin" pos="0 0 -0.12">
          <joint name="{n}_knee" axis="0 1 0" range="-2 0.5"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.12" size="0.012" mass="0.05"/>
        </body>
      </body>"""

LEGS = (("fl", 0.12, 0.1), ("fr", 0.12, -0.1), ("hl", -0.12, 0.1), ("hr", -0.12, -0.1))


def quadruped_xml() -> str:
    legs = "".join(LEG.format(n=n, x=x, y=y) for n, x, y in LEGS)
    motors = "".join(f'<motor joint="{n}_{j}" ctrlrange="-3 3"/>' for n, _, _ in LEGS for j in ("hip", "knee"))
    return f"""<mujoco model="tiny quad">
  <option timestep="0.005"/>
  <worldbody>
    <light pos="0 0 3"/>
    <geom name="ground" type="plane" size="5 5 0.1"/>
    <body name="torso" pos="0 0 0.3">
      <freejoint/>
      <geom type="box" size="0.15 0.08 0.03" mass="1.5"/>{legs}
    </body>
  </worldbody>
  <actuator>{motors}</actuator>
</mujoco>
"""


CLASS_LEG = """
      <body name="{n}_thigh" pos="{x} {y} 0" childclass="leg">
        <joint name="{n}_hip" class="hip"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.12" size="0.015" mass="0.1"/>
        <body name="{n}_shin" pos="0 0 -0.12">
          <joint name="{n}_knee" class="knee"/>
          <geom type="capsule" fromto="0 0 0 0 0 -0.12" size="0.012" mass="0.05"/>
        </body>
      </body>"""


def classed_quadruped_xml(*, elliptic: bool = True) -> str:
    """The same robot, Menagerie-style: default classes give the hips and knees their own position-servo gains and
    force ranges (the knee's through the joint's `actuatorfrcrange`), a keyframe, and a fine elliptic solve."""
    legs = "".join(CLASS_LEG.format(n=n, x=x, y=y) for n, x, y in LEGS)
    servos = "".join(f'<position class="{j}" joint="{n}_{j}"/>' for n, _, _ in LEGS for j in ("hip", "knee"))
    pose = " ".join(["0.2 -0.4"] * 4)
    option = '<option timestep="0.002" cone="elliptic" impratio="100"/>' if elliptic else ""
    return f"""<mujoco model="classed quad">
  {option}
  <default>
    <default class="leg">
      <geom condim="6"/>
      <joint axis="0 1 0"/>
      <default class="hip">
        <joint range="-1 1"/>
        <position kp="12" kv="0.3" forcerange="-4 4"/>
      </default>
      <default class="knee">
        <joint range="-2 0.5" actuatorfrcrange="-7 7"/>
        <position kp="18" kv="0.4"/>
      </default>
    </default>
  </default>
  <worldbody>
    <geom name="ground" type="plane" size="5 5 0.1"/>
    <body name="torso" pos="0 0 0.3">
      <freejoint/>
      <geom type="box" size="0.15 0.08 0.03" mass="1.5"/>{legs}
    </body>
  </worldbody>
  <actuator>{servos}</actuator>
  <keyframe><key name="stand" qpos="0 0 0.235 1 0 0 0 {pose}" ctrl="{pose}"/></keyframe>
</mujoco>
"""
