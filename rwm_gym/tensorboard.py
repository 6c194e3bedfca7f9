"""TensorBoard's writer, behind the `[tensorboard]` extra: the one place rwm-gym opens one.

`rwm-gym train`, `ppo`, `mbpo` and `shac` take `--tensorboard DIR`. Each writes its scalars through `summary_writer`,
or through Stable-Baselines3's own logger once `require_tensorboard` has passed (`rwm_gym.rl.tensorboard`), so a
missing package is the same one line everywhere, naming the extra. `tensorboard --logdir DIR` shows the curves.
"""

from __future__ import annotations

import os

INSTALL = "pip install 'rwm-gym[tensorboard]'"
"""What installs the package the writer needs."""


class TensorBoardMissing(ImportError):
    """The tensorboard package is not installed (its message is one line naming the extra)."""


def require_tensorboard() -> None:
    """Raise `TensorBoardMissing` (one line) unless the tensorboard package can be imported."""
    try:
        import tensorboard  # noqa: F401
    except ImportError:
        raise TensorBoardMissing(f"--tensorboard needs the tensorboard package: {INSTALL}") from None


def check_tensorboard(log_dir: str | os.PathLike | None, command: str) -> None:
    """For a command given `--tensorboard DIR`: exit with one line before any work when the package is missing."""
    if log_dir is None:
        return
    try:
        require_tensorboard()
    except TensorBoardMissing as error:
        raise SystemExit(f"{command}: {error}") from None


def summary_writer(log_dir: str | os.PathLike):
    """A `torch.utils.tensorboard.SummaryWriter` writing event files into `log_dir` (`TensorBoardMissing` without
    the package)."""
    require_tensorboard()
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(str(log_dir))
