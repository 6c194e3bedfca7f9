"""Batched environments behind the vector APIs our users plug into: Gymnasium's `VectorEnv`, SB3's and rsl_rl's.

Each adapts a batched core (`rwm_gym.batched_core`); `autoreset` holds what the adapters share (seeding, auto-reset);
`gym_vector_env` and `sb3_vec_env` adapt a core to each API, and `rsl_rl_vec_env` to rsl_rl's `VecEnv` (an optional
extra). They are separate modules so that a Gymnasium user does not import Stable-Baselines3 (and torch) on the way, and
nobody imports rsl_rl who does not use it.
"""
