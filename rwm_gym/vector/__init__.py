"""Batched environments behind the two vector APIs our users plug into: Gymnasium's `VectorEnv` and SB3's `VecEnv`.

`core` holds what every batched core shares (the protocol, action and `num_envs` checks, reset options, auto-reset);
`gym_vector_env` and `sb3_vec_env` adapt a core to each API. They are separate modules so that a Gymnasium user does not
import Stable-Baselines3 (and torch) on the way.
"""
