"""Build a world model of any kind from its `ModelConfig` (the only place that maps kind names to classes)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from rwm_gym.model.base import WorldModel
from rwm_gym.model.baselines import MLPModel, NoChangeModel, TransformerModel
from rwm_gym.model.config import ModelConfig, TrainConfig
from rwm_gym.model.constraints import StateConstraints
from rwm_gym.model.rssm import RSSM
from rwm_gym.model.rwm import RWM
from rwm_gym.spec import TaskSpec

MODEL_CLASSES: dict[str, type[WorldModel]] = {
    "rwm": RWM,
    "mlp": MLPModel,
    "rssm": RSSM,
    "transformer": TransformerModel,
    "no_change": NoChangeModel,
}


def model_config_for(kind: str, spec: TaskSpec, **options: Any) -> ModelConfig:
    """A ModelConfig whose sizes come from the task spec; `options` set the other fields (e.g. ensemble_size=5)."""
    return ModelConfig(
        kind=kind,
        state_dim=spec.state_dim,
        action_dim=spec.action_dim,
        contact_dim=spec.contact_dim,
        foot_dim=spec.foot_dim,
        **options,
    )


def train_config_for(kind: str, config: TrainConfig) -> TrainConfig:
    """`config` as a model of `kind` can train with it: a model whose teacher-forced pass carries a loss of its own
    (it filters with the true next state: rssm) keeps its warm-up gradients; every other kind takes `config` as it is.
    For comparisons that give every kind one trainer setting."""
    if MODEL_CLASSES[kind].filters_with_next_state and not config.warmup_gradients:
        return replace(config, warmup_gradients=True)
    return config


def build_model(config: ModelConfig, spec: TaskSpec | None = None) -> WorldModel:
    """A freshly initialised model (parameters drawn from torch's global RNG). The task spec is needed when the
    config switches on state constraints (`constraints.py`): their numbers come from it."""
    model = MODEL_CLASSES[config.kind](config)
    if (config.unit_gravity or config.joint_limits) and hasattr(model, "heads"):
        if spec is None:
            raise ValueError("unit_gravity / joint_limits need the task spec: build_model(config, spec)")
        model.heads.constraints = StateConstraints(config, spec)
    return model
