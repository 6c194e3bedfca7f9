"""rwm-gym: a learned robot world model (Robotic World Model, arXiv 2501.10100) as a Gymnasium environment.

Importing the package registers its environments with string entry points, so neither MuJoCo nor torch is imported
until an environment is made.
"""

import os

# Offscreen rendering without a display: MuJoCo picks its GL backend when first imported, so choose EGL here unless
# the user already chose one. Only where libEGL exists: with MUJOCO_GL=egl and no libEGL, `import mujoco` itself fails
# (seen on a GPU machine without libegl1), and physics needs no GL at all.
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    import ctypes.util

    if ctypes.util.find_library("EGL"):
        os.environ["MUJOCO_GL"] = "egl"

from rwm_gym.registration import register_all

__version__ = "0.1.0"

register_all()
