"""The gap report: `report.json`, `report.md` and PNG plots (per-channel residuals before/after, rollout overlay).

report.json keys: `effect` (the first named effect, `none` or `unexplained`), `reason`, `scope` (of the first:
`global`, `leg`, `joint_type`, `joint`, or null), `effects` (every named effect in order: scope, parameters, units,
uncertainty, `share_of_explained_gap`, and with `GapConfig.bootstrap` the `bootstrap` std and 95 % interval of each
parameter), `parameters` / `units` / `uncertainty` (all named parameters, flat), `bootstrap` (`resamples`, and per
named parameter its `std` and `interval` over resampled fitting episodes, `gap.bootstrap`), `joint_refit`,
`simpler_forms` (each named effect tested against a simpler one it holds, `select.prefer_simpler`), `idle_effects`
(each of several named effects tested for what it adds at the final values, `select.drop_idle`),
`explained_fraction`, `gap_before`, `gap_after` (normalised state MSE averaged over `gap_horizons`,
1, 5 and 25 steps or fewer where the held-out episodes are shorter, after the named effects),
`gap_before_per_horizon`, `gap_after_per_horizon`, `distribution_gap` (the distance between distributions of
per-window statistics of foot slip, contact timing and base motion, before and after, `gap.distribution`),
`gap_measure` (which of the two gaps heads the report, its figures and why),
`noise_floor` (the floor, the test of the nominal gap against it, the sensor-noise model), `residual` (the same test
after the named effects), `identifiability` (per effect: signal at its default magnitude / floor), `where`,
`selection_steps` (per step: floor test, candidates, decision), `candidates` (step 1's), `rejected` (parameter points
where the simulation blew up, with MuJoCo's reason), `learned_correction` (null, or the learned residual torque's
held-out gap), `held_out_episodes`, `corrected` (paths) and `plots` (paths); with a world model, `world_model`
(`error` {predictor: {N: relative error}}, `windows`, `checkpoints`, `metric`, `config`, `plot`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rwm_gym.spec import TaskSpec


def plot_channels(spec: TaskSpec, before: np.ndarray, after: np.ndarray, path: Path, horizon: int) -> None:
    """Bar chart of per-channel normalised MSE (S,) before and after the correction."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.arange(spec.state_dim)
    fig, ax = plt.subplots(figsize=(14, 4))
    ax.bar(x - 0.2, before, 0.4, label="nominal simulator")
    ax.bar(x + 0.2, after, 0.4, label="corrected simulator")
    ax.set_xticks(x, spec.state_columns, rotation=90, fontsize=7)
    ax.set_ylabel(f"normalised MSE at {horizon} steps")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_rollout(
    spec: TaskSpec, measured: np.ndarray, nominal: np.ndarray, corrected: np.ndarray, channels: list[str], path: Path
) -> None:
    """Overlay of one held-out window (H, S): measured vs nominal vs corrected re-simulation on a few channels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(channels), 1, figsize=(8, 2.2 * len(channels)), sharex=True, squeeze=False)
    t = np.arange(1, len(measured) + 1) * spec.policy_dt
    for ax, name in zip(axes[:, 0], channels):
        i = spec.state_columns.index(name)
        ax.plot(t, measured[:, i], "k.-", label="measured")
        ax.plot(t, nominal[:, i], label="nominal sim")
        ax.plot(t, corrected[:, i], label="corrected sim")
        ax.set_ylabel(name, fontsize=8)
    axes[0, 0].legend(fontsize=8)
    axes[-1, 0].set_xlabel("s after the window start")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def markdown(report: dict) -> str:
    """The human-readable report."""
    sections = (
        _verdict,
        _named_effects,
        _gap_per_horizon,
        _gap_measures,
        _learned_correction,
        _identifiability,
        _where_the_gap_lives,
        _selection_candidates,
        _rejected,
        _world_model,
        _files,
    )
    lines = [line for section in sections for line in section(report)]
    return "\n".join(lines) + "\n"


def _verdict(report: dict) -> list[str]:
    floor = report["noise_floor"]
    return [
        "# Sim-to-real gap report\n",
        f"**Verdict: `{report['effect']}`** — {report['reason']}\n",
        (
            f"Held-out gap {floor['gap']:.4g}, sensor-noise floor {floor['floor']:.4g} "
            f"(ratio {floor['ratio']:.2f}, p={floor['p_value']:.2g}; {floor['test']}).\n"
        ),
        *_headline(report.get("gap_measure")),
        *_noise_check(floor.get("noise_check")),
        *_solver(report.get("solver")),
    ]


def _headline(chosen: dict | None) -> list[str]:
    """The gap by the measure the verdict is judged by (`gap.distribution.headline`)."""
    if not chosen:
        return []
    return [
        f"Gap by the report's measure (`{chosen['measure']}`, see Gap measures): {chosen['gap_before']:.4g} before, "
        f"{chosen['gap_after']:.4g} after the correction ({chosen['explained_fraction']:.1%} explained).\n"
    ]


def _solver(solver: dict | None) -> list[str]:
    """The solver the re-simulations ran with and why (`gap.solver_check`)."""
    if not solver:
        return []
    check = solver.get("check", {})
    taken = "a converged solve" if check.get("taken") == "converged" else solver["source"]
    reason = check.get("reason", "")
    if check.get("named_set", {}).get("taken") == "own":
        reason += f"; {check['named_set']['reason']}"
    return [
        f"Re-simulated with {taken} ({solver['iterations']} iterations, {solver['ls_iterations']} line-search, "
        f"{solver['noslip_iterations']} no-slip, {solver['cone']} cone): {reason}.\n"
    ]


def _noise_check(check: dict | None) -> list[str]:
    """The sensor noise estimated from the data beside the assumed model, one row per quantity."""
    if not check:
        return []
    lines = [
        "| sensor quantity | assumed std | estimated std | estimate / assumed | resolved | floor uses |",
        "|---|---|---|---|---|---|",
    ]
    for name, row in check["quantities"].items():
        lines.append(
            f"| {name} | {row['assumed']:.3g} | {row['estimated']:.3g} | {row['ratio']:.2f} | "
            f"{'yes' if row['resolved'] else 'no (motion dominates)'} | {row['used']} |"
        )
    return [*lines, "", f"Noise estimate: {check['method']}.\n"]


def _named_effects(report: dict) -> list[str]:
    """One row per parameter of each named effect, in the order named."""
    if not report["effects"]:
        return []
    boot = report.get("bootstrap", {}).get("parameters", {})
    lines = [
        (
            "| order | effect | scope | share of explained gap | parameter | value | ± 1σ | bootstrap 95 % | unit |\n"
            "|---|---|---|---|---|---|---|---|---|"
        )
    ]
    for i, item in enumerate(report["effects"], 1):
        for name, value in item["parameters"].items():
            interval = "{:.4g} to {:.4g}".format(*boot[name]["interval"]) if name in boot else "-"
            lines.append(
                f"| {i} | {item['effect']} | {item['scope']} | {item['share_of_explained_gap']:.0%} | "
                f"{name} | {value:.4g} | {item['uncertainty'][name]:.2g} | {interval} | {item['units'][name]} |"
            )
    return [*lines, ""]


def _gap_per_horizon(report: dict) -> list[str]:
    """The held-out gap before and after correction at each horizon, and what remains against the noise floor."""
    lines = [
        f"Held-out episodes {report['held_out_episodes']}. Gap = normalised state MSE, mean over horizons.\n",
        "| horizon (steps) | gap before | gap after |\n|---|---|---|",
    ]
    for h, before in report["gap_before_per_horizon"].items():
        lines.append(f"| {h} | {before:.4g} | {report['gap_after_per_horizon'][h]:.4g} |")
    lines.append(f"| mean | {report['gap_before']:.4g} | {report['gap_after']:.4g} |\n")
    lines.append(
        f"Explained fraction: {report['explained_fraction']:.1%}; what remains is "
        f"{report['residual']['ratio']:.2f} x the noise floor of "
        f"{report['residual'].get('floor_of', 'the nominal simulator')}"
        f"{' (significantly above it)' if report['residual']['above_floor'] else ''}.\n"
    )
    return lines


def _gap_measures(report: dict) -> list[str]:
    """Both gap measures before and after the correction, the one the verdict is judged by, and why."""
    dist, chosen = report.get("distribution_gap"), report.get("gap_measure")
    if not dist or not chosen:
        return []
    lines = [
        "## Gap measures\n",
        "| measure | gap before | gap after | explained |\n|---|---|---|---|",
        f"| state_mse: normalised state MSE, step by step | {report['gap_before']:.4g} | {report['gap_after']:.4g} | "
        f"{report['explained_fraction']:.1%} |",
        f"| window_distribution: distance between distributions of window statistics | {dist['gap_before']:.4g} | "
        f"{dist['gap_after']:.4g} | {dist['explained_fraction']:.1%} |",
        f"\nThe report's gap measure is `{chosen['measure']}`: {chosen['reason']}.\n",
        "| window statistic | distance before | distance after |\n|---|---|---|",
        *(
            f"| {name} ({dist['statistics'][name]}) | {d['before']:.3g} | {d['after']:.3g} |"
            for name, d in dist["per_statistic"].items()
        ),
        f"\nDistance: {dist['metric']}; {dist['windows']} held-out windows.\n",
    ]
    return lines


def _learned_correction(report: dict) -> list[str]:
    """The learned residual torque, if one was trained: its gap reduction and its weights per joint group."""
    learned = report.get("learned_correction")
    if not learned:
        return []
    lines = ["## Learned correction (not a named effect)\n"]
    if learned["status"] != "ok":
        return [*lines, f"{learned['status']}\n"]
    lines.append(
        f"{learned['kind']}: held-out gap {learned['gap_before']:.4g} -> {learned['gap_after']:.4g} "
        f"({learned['explained_fraction']:.1%} of what the named effects left, "
        f"p={learned['p_value']:.2g}; {'kept' if learned['kept'] else 'not kept: no significant reduction'}); "
        f"weights `{Path(learned['path']).name}`. {learned['note']}.\n"
    )
    weights = learned["training"]["weights"]
    terms = list(next(iter(weights.values())))
    lines.append("| joints | " + " | ".join(terms) + " |\n|---|" + "---|" * len(terms))
    lines += [f"| {group} | " + " | ".join(f"{w[t]:.3g}" for t in terms) + " |" for group, w in weights.items()]
    return [*lines, ""]


def _identifiability(report: dict) -> list[str]:
    lines = [
        "## Identifiability from these data\n",
        "| effect | magnitude | signal / noise floor | identifiable |\n|---|---|---|---|",
    ]
    for name, item in report["identifiability"].items():
        magnitude = ", ".join(f"{v:.3g}" for v in item["magnitude"])
        lines.append(
            f"| {name} | {magnitude} | {item['signal_to_floor']:.2f} | {'yes' if item['identifiable'] else 'no'} |"
        )
    return [*lines, ""]


def _where_the_gap_lives(report: dict) -> list[str]:
    """The nominal simulator's gap by channel and by condition, and the response lag."""
    lines = [
        "## Where the gap lives (nominal simulator, held-out)\n",
        "| channel | MSE at 5 steps | share |\n|---|---|---|",
    ]
    lines += [f"| {c['channel']} | {c['mse']:.3g} | {c['share']:.1%} |" for c in report["where"]["channels_h5"]]
    lines.append("\n| condition (joints, 1 step) | residual / overall | share of samples |\n|---|---|---|")
    lines += [
        f"| {c['condition']} | {c['ratio']:.2f} | {c['fraction_of_samples']:.0%} |"
        for c in report["where"]["conditions"]
    ]
    lag = report["where"]["response_lag_s"]
    lines.append(
        f"\nResponse lag of joint velocity to target changes: measured {lag['measured'] * 1e3:.1f} ms, "
        f"nominal simulator {lag['simulated'] * 1e3:.1f} ms.\n"
    )
    return lines


def _selection_candidates(report: dict) -> list[str]:
    """Every selection step's candidates (held-out), and what the step decided."""
    lines = []
    for k, step in enumerate(report["selection_steps"], 1):
        if not step["candidates"]:
            continue
        lines.append(f"## Candidates of selection step {k} (held-out; {step.get('decision', '')})\n")
        lines.append("| effect | scope | parameters | explained | score | p |\n|---|---|---|---|---|---|")
        for c in step["candidates"]:
            values = ", ".join(f"{n}={v:.4g}" for n, v in zip(c["names"], c["values"]))
            lines.append(
                f"| {c['effect']} | {c['scope']} | {values} | {c['explained_fraction']:.1%} | "
                f"{c['score']:.3f} | {c['p_value']:.2g} |"
                if c["status"] == "ok"
                else f"| {c['effect']} | {c['scope']} | {values} | {c['status']} | | |"
            )
    return lines


def _rejected(report: dict) -> list[str]:
    if not report["rejected"]:
        return []
    return [
        "\n## Parameters rejected because the simulation blew up\n",
        *(f"- step {r['step']}, {r['effect']} ({r['scope']}): {r['point']}" for r in report["rejected"]),
    ]


def _world_model(report: dict) -> list[str]:
    if "world_model" not in report:
        return []
    return [
        "\n## Predictors on held-out measured episodes (relative error, mean over the first N rows)\n",
        world_model_table(report["world_model"]) + "\n",
        f"Metric: {report['world_model']['metric']}.\n",
    ]


def _files(report: dict) -> list[str]:
    lines = ["\n## Files\n"]
    lines += [f"- {k}: `{v}`" for k, v in {**report["corrected"], **report["plots"]}.items()]
    lines += [f"\n![{k}]({Path(v).name})" for k, v in report["plots"].items()]
    return lines


def world_model_table(section: dict) -> str:
    """Markdown table of the four (or five) predictors' errors at each horizon N (open-loop rows)."""
    horizons = list(section["windows"])
    lines = [
        "| predictor | " + " | ".join(f"N={n}" for n in horizons) + " |",
        "|---|" + "---|" * len(horizons),
        "| windows | " + " | ".join(str(section["windows"][n]) for n in horizons) + " |",
    ]
    for name, errors in section["error"].items():
        lines.append(f"| {name} | " + " | ".join(f"{errors[n]:.4f}" for n in horizons) + " |")
    return "\n".join(lines)
