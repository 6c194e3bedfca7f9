"""World models (RWM and baselines), their trainer, checkpoints and evaluation.

Public API: `WorldModel` (the step interface), `Prediction`, `ModelConfig`, `TrainConfig`, `build_model`,
`model_config_for`, `Normalizer`, and in their modules `checkpoint.save_checkpoint/load_checkpoint`,
`train.train`, `evaluate.evaluate`.
"""

from rwm_gym.model.base import Hidden, WorldModel
from rwm_gym.model.config import MODEL_KINDS, ModelConfig, TrainConfig
from rwm_gym.model.factory import build_model, model_config_for
from rwm_gym.model.normalization import Normalizer
from rwm_gym.model.prediction import Prediction

__all__ = [
    "MODEL_KINDS",
    "Hidden",
    "ModelConfig",
    "Normalizer",
    "Prediction",
    "TrainConfig",
    "WorldModel",
    "build_model",
    "model_config_for",
]
