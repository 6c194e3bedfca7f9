"""Batched environments behind the vector APIs our users plug into: Gymnasium's `VectorEnv`, SB3's and rsl_rl's.

One module per API: `gym_vector_env`, `sb3_vec_env` and `rsl_rl_vec_env` (an optional extra) each adapt a batched
core (`rwm_gym.batched_core`) to their API and hold that API's envs of every core: MuJoCo physics, dm_control,
imagination. `autoreset` holds what the adapters share (seeding, auto-reset in the same step). The modules are
separate so that a Gymnasium user does not import Stable-Baselines3 (and torch) on the way, and nobody imports rsl_rl
who does not use it; each env imports its core only when made.
"""
