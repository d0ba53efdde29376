"""Plain-text and markdown summaries of closed-loop results (the commands print these)."""

from __future__ import annotations

import csv
import io
import math

from dronefl.results.episode import EpisodeMetrics
from dronefl.results.table1 import COLUMNS, Table1Row, episode_value

#: The paper's Table I (mean, std) per (scenario, method), in Table I's column order
#: (:data:`dronefl.results.table1.METRICS`).
PAPER_TABLE1: dict[tuple[str, str], tuple[tuple[float, float], ...]] = {
    ("case1", "centralized"): (
        (0.99, 0.40),
        (14.82, 0.35),
        (0.41, 2.48),
        (0.00, 0.00),
        (22.37, 0.30),
    ),
    ("case1", "fixed"): ((2.78, 1.07), (24.65, 0.40), (0.31, 1.32), (0.40, 0.86), (31.71, 1.38)),
    ("case1", "dronefl"): ((2.59, 0.84), (24.54, 0.37), (0.29, 1.32), (0.46, 1.04), (31.12, 0.88)),
    ("case2", "centralized"): (
        (24.52, 2.10),
        (62.99, 3.71),
        (0.27, 1.68),
        (0.33, 0.66),
        (47.77, 0.54),
    ),
    ("case2", "fixed"): ((12.94, 4.80), (54.10, 2.26), (0.35, 1.37), (0.51, 1.02), (72.48, 5.80)),
    ("case2", "dronefl"): ((2.17, 1.19), (52.60, 0.32), (0.31, 1.27), (0.63, 0.57), (59.54, 1.46)),
    ("case3", "centralized"): (
        (67.94, 3.34),
        (142.12, 5.48),
        (0.20, 1.02),
        (0.06, 0.30),
        (61.71, 0.56),
    ),
    ("case3", "fixed"): (
        (14.50, 3.87),
        (58.44, 0.81),
        (12.48, 58.77),
        (0.62, 1.23),
        (78.32, 11.07),
    ),
    ("case3", "dronefl"): (
        (4.14, 2.21),
        (55.76, 0.65),
        (12.02, 57.50),
        (0.54, 1.20),
        (72.13, 4.70),
    ),
}

#: (label, value, format) rows of an episode summary.
_EPISODE_ROWS = (
    ("prediction error (m²)", lambda m: m.tracking.prediction_error, "{:.3f}"),
    ("  of those sent (m²)", lambda m: m.tracking.sent_prediction_error, "{:.3f}"),
    ("tracking distance (m²)", lambda m: m.tracking.tracking_distance, "{:.2f}"),
    ("uncertainty (Tr P)", lambda m: m.tracking.uncertainty, "{:.3f}"),
    ("speed change (m/s)", lambda m: m.tracking.speed_change, "{:.3f}"),
    ("total cost (J)", lambda m: m.tracking.total_cost, "{:.2f}"),
    ("fused-track error (m²)", lambda m: m.tracking.tracking_error, "{:.3f}"),
    ("prediction coverage", lambda m: m.tracking.prediction_coverage, "{:.3f}"),
    ("gating rejections", lambda m: m.gating_rejections, "{:d}"),
    ("FL rounds", lambda m: len(m.fl_rounds), "{:d}"),
    ("comm. (KB/s per drone)", lambda m: m.communication.mean_per_drone(), "{:.3f}"),
    ("planner (ms/step)", lambda m: m.planner_ms_per_step, "{:.2f}"),
    ("wall time (s)", lambda m: m.wall_seconds, "{:.0f}"),
    ("real-time factor (x)", lambda m: m.realtime_factor, "{:.1f}"),
)


def format_metrics(metrics: EpisodeMetrics) -> str:
    """A closed-loop episode's metrics as a short table."""
    return comparison([metrics])


def comparison(results: list[EpisodeMetrics], labels: list[str] | None = None) -> str:
    """Episodes side by side, one column per episode headed by ``labels`` (default: each
    episode's method), Table I's metrics first."""
    first = results[0]
    labels = labels or [r.method for r in results]
    lines = [
        f"{first.scenario}, {first.environment}, seed {first.seed}, {first.detector} detector, "
        f"{first.sim_seconds:.0f} s per episode",
        f"{'':26s}" + "".join(f"{label:>14s}" for label in labels),
    ]
    for label, value, fmt in _EPISODE_ROWS:
        lines.append(f"{label:26s}" + "".join(f"{fmt.format(value(r)):>14s}" for r in results))
    for r in results:
        if r.centralized_inputs:
            lines.append(f"(centralized inputs: {r.centralized_inputs})")
    return "\n".join(lines)


#: Table I's columns printed with more than two decimals (the fusion's errors are 0.01-1 m²).
_DIGITS = {"sent_prediction_error": ".3f", "tracking_error": ".3f"}


def table1_markdown(rows: list[Table1Row]) -> str:
    """Table I as markdown: ours (mean ± std over seeds) beside the paper's figures, and
    DroneFL's change against fixed distributed per scenario."""
    lines = [
        "| scenario | method | pred. error (m²) | track. distance (m²) | uncertainty (Tr P) "
        "| speed change (m/s) | total cost | pred. error of those sent (m²) "
        "| fused-track error (m²) | OSPA (m) | GOSPA (m) | paper: pred. error / track. distance |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        cells = " | ".join(
            f"{row.mean[m]:{_DIGITS.get(m, '.2f')}} ± {row.std[m]:{_DIGITS.get(m, '.2f')}}"
            for m in COLUMNS
        )
        paper = PAPER_TABLE1.get((row.scenario, row.method))
        ref = f"{paper[0][0]:.2f} / {paper[1][0]:.2f}" if paper else "–"
        lines.append(f"| {row.scenario} | {row.method} (n={len(row.seeds)}) | {cells} | {ref} |")
    lines.append("")
    by_key = {(r.scenario, r.method): r for r in rows}
    for scenario in dict.fromkeys(r.scenario for r in rows):
        ours, fixed = by_key.get((scenario, "dronefl")), by_key.get((scenario, "fixed"))
        if ours is None or fixed is None:
            continue
        change = {
            m: 100 * (ours.mean[m] / fixed.mean[m] - 1) if fixed.mean[m] else math.nan
            for m in ("prediction_error", "sent_prediction_error", "tracking_distance")
        }
        sent = change["sent_prediction_error"]
        lines.append(
            f"{scenario}: DroneFL vs fixed distributed: prediction error "
            f"{change['prediction_error']:+.1f} %"
            + (f" ({sent:+.1f} % on the predictions sent)" if math.isfinite(sent) else "")
            + f", tracking distance {change['tracking_distance']:+.1f} % "
            "(paper: -6 % to -83 % and -0.4 % to -4.6 %)."
        )
    return "\n".join(lines) + "\n"


def table1_csv(episodes: list[EpisodeMetrics], names: list[str] | None = None) -> str:
    """One CSV line per episode: scenario, method (its row's ``names``, default the episode's
    method), seed, Table I's metrics, the prediction error of the predictions sent and the
    fused-track error (m^2), OSPA and GOSPA (m), wall time (s)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(["scenario", "method", "seed", *COLUMNS, "wall_seconds"])
    names = [e.method for e in episodes] if names is None else names
    for e, name in zip(episodes, names, strict=True):
        values = [episode_value(e, m) for m in COLUMNS]
        writer.writerow([e.scenario, name, e.seed, *values, e.wall_seconds])
    return buffer.getvalue()
