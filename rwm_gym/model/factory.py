"""Build a world model of any kind from its `ModelConfig` (the only place that maps kind names to classes)."""

from __future__ import annotations

from typing import Any

from rwm_gym.model.base import WorldModel
from rwm_gym.model.baselines import MLPModel, NoChangeModel, TransformerModel
from rwm_gym.model.config import ModelConfig
from rwm_gym.model.rssm import RSSM
from rwm_gym.model.rwm import RWM
from rwm_gym.spec import TaskSpec

MODEL_CLASSES: dict[str, type[WorldModel]] = {
    "rwm": RWM, "mlp": MLPModel, "rssm": RSSM, "transformer": TransformerModel, "no_change": NoChangeModel,
}


def model_config_for(kind: str, spec: TaskSpec, **options: Any) -> ModelConfig:
    """A ModelConfig whose sizes come from the task spec; `options` set the other fields (e.g. ensemble_size=5)."""
    return ModelConfig(kind=kind, state_dim=spec.state_dim, action_dim=spec.action_dim,
                       contact_dim=spec.contact_dim, foot_dim=spec.foot_dim, **options)


def build_model(config: ModelConfig) -> WorldModel:
    """A freshly initialised model (parameters drawn from torch's global RNG)."""
    return MODEL_CLASSES[config.kind](config)
