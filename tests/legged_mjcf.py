"""A small four-legged robot written as MJCF text, for the tests of `rwm-gym spec --mjcf` (motors, no sensors,
no keyframe: everything the generator must add)."""

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
