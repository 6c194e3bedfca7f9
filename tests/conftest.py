"""Test setup shared by every test file."""

import pytest

# MuJoCo picks its OpenGL backend when first imported, whichever test file imports it first: importing rwm_gym here
# makes its choice (headless EGL where libEGL exists) before any test imports mujoco or dm_control.
import rwm_gym  # noqa: F401


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
