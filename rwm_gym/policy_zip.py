"""Loading an SB3 policy zip without running code from it.

SB3's `PPO.load` unpickles (cloudpickle) every `":serialized:"` entry of the zip's `data` JSON, and unpickling can call
any function the file names. Here each such entry is decoded by an unpickler that resolves only an allow-list of
classes and functions (SB3 policy, buffer and schedule classes, Gymnasium spaces, numpy arrays and generators, torch
activations and optimizers, this package's feature extractor); anything else refuses the file in one line. The
decoded entries go to `PPO.load` as `custom_objects`, so SB3 itself unpickles nothing; its `.pth` entries are read
by torch with `weights_only=True`.
"""

from __future__ import annotations

import base64
import io
import json
import os
import pickle
import zipfile
from pathlib import Path


class PolicyFileError(ValueError):
    """A policy file that cannot be loaded safely, or is not a policy file at all (one line)."""


# (module, name) that an entry may name. Classes here are only instantiated or referenced by the pickle, never given
# attributes (`_SafeUnpickler.load_build` refuses state on classes).
ALLOWED = frozenset(
    {
        ("stable_baselines3.common.policies", "ActorCriticPolicy"),
        ("stable_baselines3.common.policies", "ActorCriticCnnPolicy"),
        ("stable_baselines3.common.policies", "MultiInputActorCriticPolicy"),
        ("stable_baselines3.common.buffers", "RolloutBuffer"),
        ("stable_baselines3.common.buffers", "DictRolloutBuffer"),
        ("stable_baselines3.common.utils", "FloatSchedule"),
        ("stable_baselines3.common.utils", "ConstantSchedule"),
        ("stable_baselines3.common.utils", "LinearSchedule"),
        ("stable_baselines3.common.torch_layers", "FlattenExtractor"),
        ("rwm_gym.rl.ppo", "ScaledObservation"),
        ("gymnasium.spaces.box", "Box"),
        ("gymnasium.spaces.discrete", "Discrete"),
        ("gymnasium.spaces.multi_discrete", "MultiDiscrete"),
        ("gymnasium.spaces.multi_binary", "MultiBinary"),
        ("gymnasium.spaces.dict", "Dict"),
        ("gymnasium.spaces.tuple", "Tuple"),
        ("torch.optim.adam", "Adam"),
        ("torch.optim.adamw", "AdamW"),
        ("torch.optim.sgd", "SGD"),
        ("numpy", "dtype"),
        ("numpy", "ndarray"),
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("numpy.core.numeric", "_frombuffer"),
        ("numpy._core.numeric", "_frombuffer"),
        ("numpy.random._pickle", "__generator_ctor"),
        ("numpy.random._pickle", "__bit_generator_ctor"),
        ("numpy.random._pickle", "__randomstate_ctor"),
        ("numpy.random._pcg64", "PCG64"),
        ("numpy.random._generator", "Generator"),
        ("numpy.random.bit_generator", "__pyx_unpickle_SeedSequence"),
        ("numpy.random.bit_generator", "SeedSequence"),
        ("collections", "OrderedDict"),
        ("collections", "deque"),
        ("builtins", "set"),
        ("builtins", "frozenset"),
        ("builtins", "slice"),
        ("builtins", "complex"),
    }
)
ACTIVATIONS = "torch.nn.modules.activation"
"""Every class of this module (ELU, ReLU, Tanh, ...) may be named: a policy's `activation_fn`."""


class _SafeUnpickler(pickle._Unpickler):  # the Python implementation, whose opcodes can be overridden
    dispatch = dict(pickle._Unpickler.dispatch)

    def find_class(self, module: str, name: str):
        if (module, name) not in ALLOWED and module != ACTIVATIONS:
            raise PolicyFileError(f"names {module}.{name}")
        found = super().find_class(module, name)
        if module == ACTIVATIONS and not isinstance(found, type):
            raise PolicyFileError(f"names {module}.{name}")
        return found

    def load_build(self):
        if isinstance(self.stack[-2], type):
            raise PolicyFileError(f"sets attributes of the class {self.stack[-2].__name__}")
        super().load_build()

    dispatch[pickle.BUILD[0]] = load_build


def decode_entry(payload: str) -> object:
    """One `":serialized:"` value of an SB3 `data` JSON, unpickled with only the allowed globals."""
    return _SafeUnpickler(io.BytesIO(base64.b64decode(payload.encode()))).load()


def read_data(path: str | os.PathLike) -> dict:
    """The `data` JSON of an SB3 zip; a PolicyFileError for anything that is not one."""
    try:
        with zipfile.ZipFile(path) as archive:
            return json.loads(archive.read("data"))
    except FileNotFoundError:
        raise PolicyFileError(f"policy {path}: no such file") from None
    except IsADirectoryError:
        raise PolicyFileError(f"policy {path}: is a folder, not an SB3 .zip") from None
    except (zipfile.BadZipFile, KeyError, ValueError, EOFError, OSError) as err:
        raise PolicyFileError(f"policy {path}: not a readable SB3 policy zip ({type(err).__name__})") from None


def safe_custom_objects(path: str | os.PathLike) -> dict[str, object]:
    """Every serialized entry of the zip's `data`, decoded safely: `PPO.load(..., custom_objects=this)` then unpickles
    nothing. A PolicyFileError names the first entry that would need anything else."""
    objects = {}
    for key, value in read_data(path).items():
        if not (isinstance(value, dict) and ":serialized:" in value):
            continue
        try:
            objects[key] = decode_entry(value[":serialized:"])
        except PolicyFileError as err:
            raise PolicyFileError(
                f"policy {path}: entry {key!r} {err}, which loading refuses to run (only SB3 "
                f"policies, schedules, spaces and torch activations load)"
            ) from None
        except Exception as err:
            raise PolicyFileError(f"policy {path}: entry {key!r} cannot be read ({type(err).__name__})") from None
    return objects


def load_sb3(path: str | os.PathLike, *, env=None, device: str = "cpu", algorithm: str = "PPO", **kwargs):
    """`PPO.load(path, env, device)` with nothing unpickled by SB3 (see the module docstring)."""
    import stable_baselines3

    path = Path(path)
    objects = safe_custom_objects(path)
    try:
        return getattr(stable_baselines3, algorithm).load(
            path, env=env, device=device, custom_objects=objects, **kwargs
        )
    except (RuntimeError, KeyError, ValueError, EOFError, zipfile.BadZipFile, pickle.UnpicklingError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise PolicyFileError(f"policy {path}: cannot be loaded ({first})") from None


def load_policy(path: str | os.PathLike, *, env=None, device: str = "cpu", spec=None, algorithm: str = "PPO"):
    """The PPO policy of an SB3 zip, loaded without running code from it; `spec` (a TaskSpec): refuse, in one line, a
    policy whose observation or action size is not that task's (a cheetah policy given to ANYmal)."""
    model = load_sb3(path, env=env, device=device, algorithm=algorithm)
    if spec is not None:
        obs, act = model.observation_space.shape, model.action_space.shape
        if obs != (spec.observation_dim,) or act != (spec.action_dim,):
            raise PolicyFileError(
                f"policy {path} acts on observations {obs} with actions {act}; {spec.name} has "
                f"({spec.observation_dim},) and ({spec.action_dim},)"
            )
    return model
