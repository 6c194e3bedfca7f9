"""World models (RWM and baselines), their trainer, checkpoints and evaluation."""
