"""The sim-to-real gap workflow: locate, name, correct and verify a missing physical effect."""
