"""Loading an SB3 policy zip without running code from it: nothing in the file is unpickled.

SB3's `PPO.load` unpickles (cloudpickle) every `":serialized:"` entry of the zip's `data` JSON, and unpickling can call
any function the file names. This reader unpickles nothing. SB3 writes, beside each pickled entry, its fields as
plain JSON (`"net_arch"`, `"activation_fn": "<class 'torch.nn.modules.activation.ELU'>"`, a Box's `dtype`, `_shape`,
`low` and `high`, a schedule's `"ConstantSchedule(val=0.2)"`); the policy is rebuilt from those fields alone, each
class looked up by its exact qualified name in a fixed table (`ACTIVATIONS`, `EXTRACTORS`, `OPTIMIZERS`), and the
weights (`policy.pth`, `policy.optimizer.pth`) are read by torch with `weights_only=True`. Pickled entries this
reader does not need (the training envs' last observations, episode statistics, anything a file adds) are ignored
without being decoded. Zip members are capped by their declared size and compression ratio before inflating
(`rwm_gym.untrusted.read_zip_member`), and the network the file describes must fit the weights it carries.

What loads: PPO with SB3's `ActorCriticPolicy` (`"MlpPolicy"`) on Box spaces, the policies rwm-gym writes. A Box's
bounds are read from the printed arrays (8 significant digits; the bounds rwm-gym's tasks use, +-1 and +-inf, exactly).
"""

from __future__ import annotations

import io
import itertools
import json
import math
import os
import re
import zipfile
from pathlib import Path

import numpy as np

from rwm_gym.untrusted import memory_cap_bytes, read_zip_member, regular_file


class PolicyFileError(ValueError):
    """A policy file that cannot be loaded safely, or is not a policy file at all (one line)."""


DATA_LIMIT = 64 << 20
"""Most bytes the `data` JSON may hold (a policy with its run state at 4096 envs: about 1 MB)."""
WEIGHTS = ("policy.pth", "policy.optimizer.pth")

ACTIVATIONS = {
    f"torch.nn.modules.activation.{name}": name
    for name in ("ELU", "ReLU", "Tanh", "LeakyReLU", "GELU", "SiLU", "Sigmoid", "Softplus", "Mish", "SELU", "CELU")
}
"""A policy's `activation_fn`: qualified name -> `torch.nn` attribute."""
EXTRACTORS = {
    f"{module}.{name}": (module, name)
    for module, name in (
        ("stable_baselines3.common.torch_layers", "FlattenExtractor"),
        ("rwm_gym.rl.ppo", "ScaledObservation"),
    )
}
"""A policy's `features_extractor_class`: qualified name -> (module, attribute), imported only from this table."""
OPTIMIZERS = {f"torch.optim.{m}.{n}": n for m, n in (("adam", "Adam"), ("adamw", "AdamW"), ("sgd", "SGD"))}
POLICY_KWARGS_PLAIN = {
    "ortho_init": bool,
    "use_sde": bool,
    "log_std_init": float,
    "full_std": bool,
    "use_expln": bool,
    "squash_output": bool,
    "share_features_extractor": bool,
    "normalize_images": bool,
}
OPTIMIZER_KWARGS = {"eps": float, "weight_decay": float, "betas": list, "amsgrad": bool, "momentum": float}
SETTINGS = {  # the `data` fields copied onto the model, with their JSON types (None allowed where listed)
    "verbose": (int,),
    "num_timesteps": (int,),
    "_total_timesteps": (int,),
    "_num_timesteps_at_start": (int,),
    "seed": (int, None),
    "start_time": (int, float),  # ns since the epoch (0.0 before learning)
    "_episode_num": (int,),
    "use_sde": (bool,),
    "sde_sample_freq": (int,),
    "_current_progress_remaining": (float,),
    "_stats_window_size": (int,),
    "_n_updates": (int,),
    "n_envs": (int,),
    "n_steps": (int,),
    "gamma": (float,),
    "gae_lambda": (float,),
    "ent_coef": (float,),
    "vf_coef": (float,),
    "max_grad_norm": (float,),
    "batch_size": (int,),
    "n_epochs": (int,),
    "normalize_advantage": (bool,),
    "target_kl": (float, None),
    "action_noise": (None,),
}
_CLASS_TEXT = re.compile(r"<class '([A-Za-z_][\w.]*)'>")
TASK_ID = re.compile(r"[A-Za-z][\w.:-]{0,99}")
"""A task's physics env id as a policy names it (e.g. `Go2-MuJoCo-v0`)."""


def read_zip(path: str | os.PathLike) -> tuple[dict, dict[str, bytes]]:
    """The `data` JSON of an SB3 zip and its weight members' bytes (not yet decoded); a PolicyFileError for anything
    that is not one, a bomb, or a member over the limits."""
    path = Path(path)
    try:
        regular_file(path, "policy")
    except (FileNotFoundError, ValueError) as err:
        raise PolicyFileError(str(err).replace("is a folder, not a file", "is a folder, not an SB3 .zip")) from None
    try:
        with zipfile.ZipFile(path) as archive:
            members = {info.filename: info for info in archive.infolist()}
            if "data" not in members:
                raise PolicyFileError(f"policy {path}: not an SB3 policy zip (no 'data' entry)")
            limit = memory_cap_bytes() // 4
            raw = read_zip_member(archive, members["data"], DATA_LIMIT)
            weights = {name: read_zip_member(archive, members[name], limit) for name in WEIGHTS if name in members}
    except PolicyFileError:
        raise
    except ValueError as err:  # read_zip_member's refusals
        raise PolicyFileError(f"policy {path}: {err}") from None
    except (zipfile.BadZipFile, EOFError, OSError, RuntimeError, NotImplementedError) as err:
        raise PolicyFileError(f"policy {path}: not a readable SB3 policy zip ({type(err).__name__})") from None
    try:
        data = json.loads(raw)
    except (ValueError, RecursionError):  # RecursionError: arrays nested thousands deep
        raise PolicyFileError(f"policy {path}: not a readable SB3 policy zip (its data is not JSON)") from None
    if not isinstance(data, dict):
        raise PolicyFileError(f"policy {path}: not an SB3 policy zip (data is not a JSON object)")
    if "policy.pth" not in weights:
        raise PolicyFileError(f"policy {path}: not an SB3 policy zip (no 'policy.pth' entry)")
    return data, weights


def read_data(path: str | os.PathLike) -> dict:
    """The `data` JSON of an SB3 zip; a PolicyFileError for anything that is not one."""
    return read_zip(path)[0]


class _Bad(ValueError):
    """A field of `data` that this reader refuses; the message says why, the caller names the entry."""


def _number(value, kind: type, what: str):
    what = f"{what} " if what else ""
    if kind is bool:
        if not isinstance(value, bool):
            raise _Bad(f"{what}is {value!r}, not true or false")
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (kind is int and not isinstance(value, int)):
        raise _Bad(f"{what}is {value!r}, not a{'n integer' if kind is int else ' number'}")
    if not math.isfinite(value):
        raise _Bad(f"{what}is {value!r}, not finite")
    return kind(value)


def _setting(key: str, value):
    kinds = SETTINGS[key]
    if value is None:
        if None not in kinds:
            raise _Bad(f"is null, not a {kinds[0].__name__}")
        return None
    if isinstance(value, dict):
        raise _Bad("is a pickled object, where rwm-gym reads a plain value")
    numeric = [k for k in kinds if k is not None]
    if not numeric:
        raise _Bad(f"is {value!r}, where rwm-gym reads null")
    kind = int if int in numeric and type(value) is int else numeric[-1]
    return _number(value, kind, "")


def _class_name(text, table: dict, what: str) -> object:
    """The table's entry for a class written as "<class 'module.Name'>" (its exact qualified name)."""
    match = _CLASS_TEXT.fullmatch(text) if isinstance(text, str) else None
    if match is None or match.group(1) not in table:
        raise _Bad(f"{what} {text!r} is not one rwm-gym loads ({', '.join(sorted(table))})")
    return table[match.group(1)]


def _floats(value, what: str) -> np.ndarray:
    """A flat float array from a JSON list or from numpy's printed form ("[-1. -1. inf]")."""
    if isinstance(value, list):
        tokens = value
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        tokens = [value]
    elif isinstance(value, str) and "..." not in value:
        tokens = value.replace("[", " ").replace("]", " ").split()
    else:
        raise _Bad(f"{what} is not a list of numbers")
    try:
        return np.array([float(t) for t in tokens if not isinstance(t, (bool, list, dict))], dtype=np.float64)
    except (TypeError, ValueError):
        raise _Bad(f"{what} is not a list of numbers") from None


def _box(entry) -> object:
    from gymnasium import spaces

    if not isinstance(entry, dict) or entry.get(":type:") != "<class 'gymnasium.spaces.box.Box'>":
        kind = entry.get(":type:") if isinstance(entry, dict) else type(entry).__name__
        raise _Bad(f"is {kind}, not a gymnasium Box (the only space rwm-gym loads)")
    dtype, shape = entry.get("dtype"), entry.get("_shape")
    if dtype not in ("float32", "float64"):
        raise _Bad(f"has dtype {dtype!r}, not float32 or float64")
    if not (isinstance(shape, list) and 0 < len(shape) <= 4 and all(type(n) is int and 0 < n for n in shape)):
        raise _Bad(f"has shape {shape!r}, not a list of positive sizes")
    bounds = [_floats(entry.get(side), side) for side in ("low", "high")]
    size = math.prod(shape)
    if any(b.size != size for b in bounds):
        raise _Bad(f"has bounds whose sizes are not its shape {tuple(shape)}")
    low, high = (b.reshape(shape).astype(dtype) for b in bounds)
    if np.isnan(low).any() or np.isnan(high).any() or (low > high).any():
        raise _Bad("has bounds that are NaN or low > high")
    return spaces.Box(low=low, high=high, shape=tuple(shape), dtype=np.dtype(dtype))


def _schedule(entry):
    """A number, or SB3's FloatSchedule / ConstantSchedule / LinearSchedule rebuilt from its printed fields."""
    from stable_baselines3.common.utils import ConstantSchedule, FloatSchedule, LinearSchedule

    def linear(start: float, end: float, fraction: float):
        if fraction <= 0:
            raise _Bad(f"has end_fraction {fraction}, not > 0")
        return FloatSchedule(LinearSchedule(start, end, fraction))

    if isinstance(entry, (int, float)) and not isinstance(entry, bool):
        return _number(entry, float, "the value")
    kind = entry.get(":type:") if isinstance(entry, dict) else None
    prefix = "<class 'stable_baselines3.common.utils."
    if kind == f"{prefix}FloatSchedule'>":
        text, number = entry.get("value_schedule"), r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)"
        if isinstance(text, str) and (m := re.fullmatch(rf"ConstantSchedule\(val={number}\)", text)):
            return FloatSchedule(ConstantSchedule(float(m.group(1))))
        pattern = rf"LinearSchedule\(start={number}, end={number}, end_fraction={number}\)"
        if isinstance(text, str) and (m := re.fullmatch(pattern, text)):
            return linear(*(float(g) for g in m.groups()))
        raise _Bad(f"wraps {text!r}, not a constant or linear schedule")
    if kind == f"{prefix}ConstantSchedule'>":
        return FloatSchedule(ConstantSchedule(_number(entry.get("val"), float, "val")))
    if kind == f"{prefix}LinearSchedule'>":
        return linear(*(_number(entry.get(k), float, k) for k in ("start", "end", "end_fraction")))
    raise _Bad(f"is {kind or type(entry).__name__}, not a number or an SB3 schedule")


def _policy_class(entry) -> None:
    init = entry.get("__init__") if isinstance(entry, dict) else None
    if not (
        isinstance(entry, dict)
        and entry.get("__module__") == "stable_baselines3.common.policies"
        and isinstance(init, str)
        and init.startswith("<function ActorCriticPolicy.__init__ ")
    ):
        raise _Bad("is not SB3's ActorCriticPolicy ('MlpPolicy'), the only policy rwm-gym loads")


def _policy_kwargs(entry, observation_dim: int) -> dict:
    import importlib

    import torch

    if entry is None:
        return {}
    if not isinstance(entry, dict) or entry.get(":type:", "<class 'dict'>") != "<class 'dict'>":
        raise _Bad(f"is {entry.get(':type:') if isinstance(entry, dict) else type(entry).__name__}, not a dict")
    kwargs: dict = {}
    for key, value in entry.items():
        if key in (":type:", ":serialized:", "device"):
            continue
        if key == "net_arch":
            kwargs[key] = _net_arch(value)
        elif key == "activation_fn":
            kwargs[key] = getattr(torch.nn, _class_name(value, ACTIVATIONS, "activation"))
        elif key == "features_extractor_class":
            module, name = _class_name(value, EXTRACTORS, "features extractor")
            kwargs[key] = getattr(importlib.import_module(module), name)
        elif key == "optimizer_class":
            kwargs[key] = getattr(torch.optim, _class_name(value, OPTIMIZERS, "optimizer"))
        elif key == "features_extractor_kwargs":
            kwargs[key] = _extractor_kwargs(value, observation_dim)
        elif key == "optimizer_kwargs":
            kwargs[key] = _optimizer_kwargs(value)
        elif key in POLICY_KWARGS_PLAIN:
            kwargs[key] = _number(value, POLICY_KWARGS_PLAIN[key], key)
        else:
            raise _Bad(f"has {key!r}, which rwm-gym does not load")
    if "features_extractor_kwargs" in kwargs and "features_extractor_class" not in kwargs:
        raise _Bad("has features_extractor_kwargs without features_extractor_class")
    return kwargs


def _net_arch(value) -> object:
    def layers(v, what):
        if not (isinstance(v, list) and len(v) <= 16 and all(type(n) is int and 0 < n <= 65536 for n in v)):
            raise _Bad(f"{what} is {v!r}, not a list of up to 16 layer sizes")
        return list(v)

    if isinstance(value, dict) and set(value) <= {"pi", "vf"}:
        return {k: layers(v, f"net_arch[{k!r}]") for k, v in value.items()}
    return layers(value, "net_arch")


def _extractor_kwargs(value, observation_dim: int) -> dict:
    if not isinstance(value, dict) or not set(value) <= {"mean", "std", "task"}:
        raise _Bad("features_extractor_kwargs holds other than mean, std and task")
    out = {}
    if "task" in value:  # the physics env id the policy was made for
        task = value["task"]
        if not (task is None or (isinstance(task, str) and TASK_ID.fullmatch(task))):
            raise _Bad(f"features_extractor_kwargs task is {str(task)[:80]!r}, not an env id")
        out["task"] = task
    for key, v in value.items():
        if key == "task":
            continue
        array = _floats(v, key)
        if array.size != observation_dim or not np.isfinite(array).all():
            raise _Bad(f"features_extractor_kwargs {key} is not {observation_dim} finite numbers")
        out[key] = array.tolist()
    if "std" in out and min(out["std"]) <= 0:
        raise _Bad("features_extractor_kwargs std is not > 0")
    return out


def _optimizer_kwargs(value) -> dict:
    if not isinstance(value, dict):
        raise _Bad("optimizer_kwargs is not a dict")
    out = {}
    for key, v in value.items():
        if key not in OPTIMIZER_KWARGS:
            raise _Bad(f"optimizer_kwargs has {key!r}, which rwm-gym does not load")
        if OPTIMIZER_KWARGS[key] is list:
            if not (isinstance(v, list) and len(v) == 2):
                raise _Bad(f"optimizer_kwargs {key} is not two numbers")
            out[key] = tuple(_number(x, float, key) for x in v)
        else:
            out[key] = _number(v, OPTIMIZER_KWARGS[key], key)
    return out


def _parameter_count(kwargs: dict, observation_dim: int, action_dim: int) -> int:
    """Parameters of the actor-critic `kwargs` describe (SB3's default [64, 64] when none is given)."""
    arch = kwargs.get("net_arch", [64, 64])
    pi, vf = (arch.get("pi", []), arch.get("vf", [])) if isinstance(arch, dict) else (arch, arch)
    total = 0
    for layers, out in ((pi, action_dim), (vf, 1)):
        sizes = [observation_dim, *layers, out]
        total += sum(a * b + b for a, b in itertools.pairwise(sizes))
    return total + action_dim


def settings(path: str | os.PathLike, data: dict, weight_bytes: int) -> dict:
    """The attributes a PPO model takes from `data`, each checked; a PolicyFileError naming the first bad entry."""
    path = Path(path)
    out: dict = {}
    current = "policy_class"
    try:
        _policy_class(data.get("policy_class"))
        for current in ("observation_space", "action_space"):
            if current not in data:
                raise _Bad("is missing")
            out[current] = _box(data[current])
        obs_dim, act_dim = math.prod(out["observation_space"].shape), math.prod(out["action_space"].shape)
        current = "policy_kwargs"
        out[current] = _policy_kwargs(data.get(current), obs_dim)
        for current in ("learning_rate", "lr_schedule", "clip_range"):
            if current in data:
                out[current] = _schedule(data[current])
        current = "clip_range_vf"
        if data.get(current) is not None:
            out[current] = _schedule(data[current])
        for current in SETTINGS:
            if current in data:
                out[current] = _setting(current, data[current])
        current = "rollout_buffer_kwargs"
        if data.get(current) not in (None, {}):
            raise _Bad("is not empty (rwm-gym's policies set none)")
    except _Bad as err:
        raise PolicyFileError(f"policy {path}: entry {current!r} {err}; loading rebuilds only what it knows") from None
    count = _parameter_count(out["policy_kwargs"], obs_dim, act_dim)
    if 4 * count > 2 * weight_bytes + (1 << 20):
        raise PolicyFileError(
            f"policy {path}: entry 'policy_kwargs' describes a network of {count} parameters, more than its "
            f"policy.pth ({weight_bytes} bytes) holds"
        )
    buffer = 4 * out.get("n_steps", 2048) * out.get("n_envs", 1) * (obs_dim + act_dim + 8)
    if buffer > memory_cap_bytes():
        raise PolicyFileError(f"policy {path}: n_steps x n_envs ask for a {buffer / 2**30:.0f} GiB rollout buffer")
    return out


def _weights(path: Path, weights: dict[str, bytes], device: str) -> dict:
    import torch

    params = {}
    for name, payload in weights.items():
        try:
            params[name.removesuffix(".pth")] = torch.load(io.BytesIO(payload), map_location=device, weights_only=True)
        except Exception as err:  # torch's weights-only unpickler refuses anything but tensors and plain containers
            first = (str(err).strip().splitlines() or [type(err).__name__])[0]
            raise PolicyFileError(f"policy {path}: entry {name!r} is not plain weights ({first[:200]})") from None
    return params


def load_sb3(path: str | os.PathLike, *, env=None, device: str = "cpu", algorithm: str = "PPO"):
    """The PPO model of an SB3 zip, rebuilt from its JSON fields and weights (see the module docstring); `env`, when
    given, must have the saved spaces and becomes the model's env, as with `PPO.load(path, env)`."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.common.utils import check_for_correct_spaces

    path = Path(path)
    if algorithm != "PPO":
        raise PolicyFileError(f"policy {path}: rwm-gym loads PPO policies, not {algorithm}")
    data, weights = read_zip(path)
    saved = settings(path, data, len(weights["policy.pth"]))
    params = _weights(path, weights, device)
    if env is not None:
        env = PPO._wrap_env(env, saved.get("verbose", 0))
        try:
            check_for_correct_spaces(env, saved["observation_space"], saved["action_space"])
        except ValueError as err:
            raise PolicyFileError(f"policy {path}: {' '.join(str(err).split())}") from None
        saved["n_envs"] = env.num_envs
    try:
        model = PPO(policy=ActorCriticPolicy, env=env, device=device, _init_setup_model=False)
        model.__dict__.update(saved)
        model._setup_model()
        model.set_parameters(params, exact_match=len(params) == len(WEIGHTS), device=device)
    except (RuntimeError, KeyError, ValueError, TypeError, AssertionError) as err:
        first = " ".join(str(err).split()) or type(err).__name__
        raise PolicyFileError(
            f"policy {path}: its weights do not fit the network it describes ({first[:200]})"
        ) from None
    if model.use_sde:
        model.policy.reset_noise()
    return model


def load_policy(path: str | os.PathLike, *, env=None, device: str = "cpu", spec=None, algorithm: str = "PPO"):
    """The PPO policy of an SB3 zip, loaded without running code from it; `spec` (a TaskSpec): refuse, in one line, a
    policy whose observation or action size is not that task's (a cheetah policy given to ANYmal)."""
    model = load_sb3(path, env=env, device=device, algorithm=algorithm)
    if spec is not None:
        check_spaces(model, spec, path)
    return model


def check_spaces(model, spec, path: str | os.PathLike) -> None:
    """Refuse, in one line, a loaded policy whose observation or action size is not `spec`'s."""
    obs, act = model.observation_space.shape, model.action_space.shape
    if obs != (spec.observation_dim,) or act != (spec.action_dim,):
        raise PolicyFileError(
            f"policy {path} acts on observations {obs} with actions {act}; {spec.name} has "
            f"({spec.observation_dim},) and ({spec.action_dim},)"
        )
