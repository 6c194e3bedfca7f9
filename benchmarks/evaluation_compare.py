"""Several world models' `rwm-gym evaluate` results side by side: one panel per held-out source, one table.

Each run is `LABEL=DIR`, DIR an `rwm-gym evaluate --out` folder of the same sources, horizons, window count and seed
(then every model is scored on the same windows, and the floors are shared). A panel draws each model's running mean
of the per-step error over the longest horizon's windows and the "no change" floor at the reported horizons. Writes
`<out>.png` and `<out>.md` (relative L1 at every reported horizon, and the floors).

    python benchmarks/evaluation_compare.py shipped=runs/eval_a "100-step forecasts=runs/eval_b" \
        --out benchmarks/figures/forecast_length
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from rwm_gym.atomic import save_png, write_text


def parse_run(text: str) -> tuple[str, Path]:
    """`LABEL=DIR` -> (label, folder holding evaluation.json)."""
    label, sep, folder = text.partition("=")
    if not sep or not label or not folder:
        raise argparse.ArgumentTypeError(f"{text!r}: expected LABEL=DIR")
    if not (Path(folder) / "evaluation.json").is_file():
        raise argparse.ArgumentTypeError(f"{folder}: no evaluation.json (an `rwm-gym evaluate --out` folder)")
    return label, Path(folder)


def load_sources(folder: Path) -> dict[str, dict]:
    """{source name: result}; a one-source evaluation is named after its data file."""
    saved = json.loads((folder / "evaluation.json").read_text())
    return saved["sources"] if "sources" in saved else {Path(saved["data"]).stem: saved}


def table(runs: dict[str, dict[str, dict]], sources: list[str]) -> list[str]:
    """Markdown rows: per source each model's error at the reported horizons, then the two floors."""
    rows = []
    for source in sources:
        first = next(iter(runs.values()))[source]
        horizons = first["horizons"]
        rows += [
            f"**{source}** ({first['episodes']} episodes; windows per horizon: "
            + ", ".join(f"N={n}: {first['windows'][str(n)]}" for n in horizons)
            + ")",
            "",
            "| model | " + " | ".join(f"N={n}" for n in horizons) + " |",
            "|---|" + "---|" * len(horizons),
        ]
        for label, result in runs.items():
            errors = result[source]["error"]
            rows.append(f"| {label} | " + " | ".join(f"{errors[str(n)]:.3f}" for n in horizons) + " |")
        for floor in ("no change", "predict the mean"):
            rows.append(
                f"| *{floor}* | " + " | ".join(f"{first['floors'][floor][str(n)]:.3f}" for n in horizons) + " |"
            )
        rows.append("")
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=parse_run, metavar="LABEL=DIR")
    parser.add_argument("--out", type=Path, required=True, help="path stem of the PNG and the table")
    args = parser.parse_args(argv)
    runs = {label: load_sources(folder) for label, folder in args.runs}
    sources = [s for s in next(iter(runs.values())) if all(s in r for r in runs.values())]
    if not sources:
        parser.error("the runs share no held-out source")
    for source in sources:  # the floors and the comparison hold only on the same windows
        # which episodes: their ids, or only their count where a file predates the ids
        episodes = "episode_ids" if all("episode_ids" in r[source] for r in runs.values()) else "episodes"
        settings = {
            label: (r[source]["horizons"], r[source]["windows"], r[source][episodes]) for label, r in runs.items()
        }
        if len(set(map(repr, settings.values()))) > 1:
            parser.error(
                f"{source}: the runs were not evaluated on the same windows (horizons, windows, {episodes}: "
                + "; ".join(f"{label} {value}" for label, value in settings.items())
                + ")"
            )
    columns = min(len(sources), 2)
    grid_rows = math.ceil(len(sources) / columns)
    fig, axes = plt.subplots(grid_rows, columns, figsize=(6 * columns, 4 * grid_rows), squeeze=False)
    for ax, source in zip(axes.flat, sources):
        for label, result in runs.items():
            curve = result[source]["running_mean"]
            ax.plot(range(1, len(curve) + 1), curve, label=label)
        first = next(iter(runs.values()))[source]
        ax.plot(
            first["horizons"],
            [first["floors"]["no change"][str(n)] for n in first["horizons"]],
            "k--o",
            ms=3,
            label="no change",
        )
        ax.set_title(source)
        ax.set_xlabel("horizon N (steps open-loop)")
        ax.set_ylabel("relative L1, mean over steps 1..N")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(sources) :]:
        ax.axis("off")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_png(fig, args.out.with_suffix(".png"))
    rows = table(runs, sources)
    write_text(args.out.with_suffix(".md"), "\n".join(rows))
    print("\n".join(rows))


if __name__ == "__main__":
    main()
