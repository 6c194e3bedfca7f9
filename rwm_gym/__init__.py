"""rwm-gym: a learned robot world model (Robotic World Model, arXiv 2501.10100) as a Gymnasium environment.

Importing the package registers its environments with string entry points, so neither MuJoCo nor torch is imported
until an environment is made.
"""

from rwm_gym.registration import register_all

__version__ = "0.1.0"

register_all()
