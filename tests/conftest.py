"""Test setup shared by every test file."""

import os

# MuJoCo picks its OpenGL backend when first imported, whichever test file imports it first: headless EGL unless the
# environment chose one (rwm_gym does the same on import, but some tests import mujoco or dm_control before it).
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "egl"
