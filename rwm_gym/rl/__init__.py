"""Learners and their evaluation: PPO and MBPO on the imagined env, behaviour cloning, physics evaluation of
policies."""
