"""The task logic shared by the physics and the imagined environments: commands, observation, reward, termination."""
