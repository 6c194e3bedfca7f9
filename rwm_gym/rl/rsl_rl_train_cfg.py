"""rsl_rl's `train_cfg` dict from `PPOConfig`: the same PPO settings (RWM's, as Isaac Lab writes them) for rsl_rl's
`OnPolicyRunner` as for rwm-gym's own Stable-Baselines3 PPO.

rsl_rl (`rsl-rl-lib` 5.x) reads its configuration as a string-keyed dict with class names; this builds it in one
place from the typed config, so a typo is an error here and not a `KeyError` deep in the runner. Needs no rsl_rl.
"""

from __future__ import annotations

import math

from rwm_gym.rl.ppo import PPOConfig


def rsl_rl_train_cfg(
    config: PPOConfig | None = None, *, obs_normalization: bool = True, save_interval: int = 50, run_name: str = ""
) -> dict:
    """The runner's `train_cfg` for `config` (default `PPOConfig()`; its `num_envs` belongs to the env, not here).

    obs_normalization: rsl_rl's running mean/std normaliser on the actor's and critic's inputs. The raw observation
    mixes m/s, rad and rad/s of very different spread; rwm-gym's SB3 PPO divides by the spec's fixed scale, and
    rsl_rl's own normaliser (saved in its checkpoints and exports) plays that part here.
    save_interval: iterations between the runner's checkpoints in its log_dir.
    """
    config = config if config is not None else PPOConfig()
    unsupported = {
        "critic_warmup_steps": config.critic_warmup_steps != 0,
        "positive_reward_only": config.positive_reward_only,
        "lr_anneal_fraction": config.lr_anneal_fraction != 0,
        "use_sde": config.use_sde,
    }
    for name, used in unsupported.items():
        if used:
            raise ValueError(f"PPOConfig.{name} has no counterpart in rsl_rl's PPO; leave it at its default")
    if config.symmetry:
        raise ValueError(
            "PPOConfig.symmetry is not passed on to rsl_rl (its symmetry_cfg, which needs an augmentation "
            "function, is not built here); leave it at its default"
        )
    model = {
        "class_name": "MLPModel",
        "hidden_dims": list(config.net_arch),
        "activation": config.activation,
        "obs_normalization": obs_normalization,
    }
    return {
        "num_steps_per_env": config.n_steps,
        "save_interval": save_interval,
        "run_name": run_name,
        "obs_groups": {"actor": ["policy"], "critic": ["policy"]},
        "actor": {
            **model,
            "distribution_cfg": {
                "class_name": "GaussianDistribution",
                "init_std": math.exp(config.log_std_init),
                "std_type": "scalar",
            },
        },
        "critic": dict(model),
        "algorithm": {
            "class_name": "PPO",
            "num_learning_epochs": config.n_epochs,
            "num_mini_batches": config.num_minibatches,
            "clip_param": config.clip_range,
            "gamma": config.gamma,
            "lam": config.gae_lambda,
            "value_loss_coef": config.vf_coef,
            "entropy_coef": config.ent_coef,
            "learning_rate": config.learning_rate,
            "max_grad_norm": config.max_grad_norm,
            "use_clipped_value_loss": True,
            "schedule": "adaptive" if config.target_kl > 0 else "fixed",
            "desired_kl": config.target_kl if config.target_kl > 0 else None,
            "normalize_advantage_per_mini_batch": False,
        },
    }
