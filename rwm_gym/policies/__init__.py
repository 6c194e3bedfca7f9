"""Scripted controllers that drive the physics env: random actions, the trot gait, the excitation policy, an arm's
reach."""
