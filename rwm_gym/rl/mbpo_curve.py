"""The MBPO loop's curve: physics tracking against physics samples (beside a model-free run's) and imagined steps, and
the model's error on each iteration's fresh data (`mbpo.png`)."""

from __future__ import annotations

from pathlib import Path

from rwm_gym.atomic import save_png

TRACKING_TARGET = 0.80
"""The tracking score the paper's comparison asks MBPO-PPO to reach (drawn as a dashed line)."""


def read_curve(path: str | Path) -> list[tuple[int, float]]:
    """(timesteps, tracking) rows of a physics-tracking curve CSV."""
    import csv

    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows or not {"timesteps", "tracking"} <= set(rows[0]):
        raise ValueError(f"{path}: a curve CSV needs 'timesteps' and 'tracking' columns")
    return [(int(float(r["timesteps"])), float(r["tracking"])) for r in rows]


def plot_curve(log: list[dict], path: Path, model_free: list[tuple[int, float]] | None = None) -> None:
    """Physics tracking against physics samples (beside model-free PPO's curve, if given) and against imagined steps
    (wall-clock minutes marked), and the fresh-data model error per iteration; written atomically."""

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 3.8))
    tracking = [r["tracking"] for r in log]
    axes[0].plot([r["physics_samples"] / 1e6 for r in log], tracking, "o-", label="MBPO-PPO")
    if model_free:
        axes[0].plot([s / 1e6 for s, _ in model_free], [t for _, t in model_free], "-", label="model-free PPO")
    axes[0].set_xlabel("physics samples (M)")
    axes[0].set_title("physics tracking score")
    axes[0].legend()
    imagined = [r["imagined_steps"] / 1e6 for r in log]
    axes[1].plot(imagined, tracking, "o-")
    for r, x, y in list(zip(log, imagined, tracking))[:: max(1, len(log) // 6)]:
        axes[1].annotate(
            f"{r['wall_s'] / 60:.0f} min", (x, y), textcoords="offset points", xytext=(0, 6), fontsize=7, ha="center"
        )
    for ax in axes[:2]:
        ax.axhline(TRACKING_TARGET, color="grey", linestyle="--", linewidth=0.8)
    axes[1].set_xlabel("imagined steps (M)")
    axes[1].set_title("physics tracking against imagined steps (wall time)")
    measured = [r for r in log if r["model_error_fresh"]]
    for horizon in measured[0]["model_error_fresh"] if measured else []:
        axes[2].plot(
            [r["iteration"] for r in measured],
            [r["model_error_fresh"][horizon] for r in measured],
            "o-",
            label=f"{horizon} steps",
        )
    axes[2].set_xlabel("iteration")
    axes[2].set_title("model error on the policy's fresh physics data")
    if measured:
        axes[2].legend()
    fig.tight_layout()
    save_png(fig, path, dpi=100)
