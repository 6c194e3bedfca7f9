"""Test setup shared by every test file."""

import os

import pytest

# MuJoCo picks its OpenGL backend when first imported, whichever test file imports it first: headless EGL unless the
# environment chose one (rwm_gym does the same on import, but some tests import mujoco or dm_control before it).
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "egl"


@pytest.fixture(autouse=True)
def one_thread():
    """Run torch on one thread: tiny models are slower with more, and the test machine's cores are shared."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
