"""Compatibility: SB3 zips saved before PPO moved to `rwm_gym.rl.ppo` name this module in their pickled policy
settings (the observation scaling below); this alias lets `PPO.load` read them. New zips name `rwm_gym.rl.ppo`."""

from rwm_gym.rl.ppo import ScaledObservation  # noqa: F401
