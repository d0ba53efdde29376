"""Table I: closed-loop tracking for Cases 1-3 x {centralized, fixed, DroneFL} x seeds.

Each episode writes its own folder ``<out>/case<N>/<method>/seed<K>/``; finished episodes
(with a ``metrics.json``) are reused, so an interrupted table resumes where it stopped.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from dronefl.experiments.track import TRACK_METHODS, TrackConfig, run_episode
from dronefl.io import atomic_write_text

METRICS = ("prediction_error", "tracking_distance", "uncertainty", "speed_change", "total_cost")

#: The paper's Table I (mean ± std), for the side-by-side comparison.
PAPER = {
    (1, "centralized"): ((0.99, 0.40), (14.82, 0.35), (0.41, 2.48), (0.00, 0.00), (22.37, 0.30)),
    (1, "fixed"): ((2.78, 1.07), (24.65, 0.40), (0.31, 1.32), (0.40, 0.86), (31.71, 1.38)),
    (1, "dronefl"): ((2.59, 0.84), (24.54, 0.37), (0.29, 1.32), (0.46, 1.04), (31.12, 0.88)),
    (2, "centralized"): ((24.52, 2.10), (62.99, 3.71), (0.27, 1.68), (0.33, 0.66), (47.77, 0.54)),
    (2, "fixed"): ((12.94, 4.80), (54.10, 2.26), (0.35, 1.37), (0.51, 1.02), (72.48, 5.80)),
    (2, "dronefl"): ((2.17, 1.19), (52.60, 0.32), (0.31, 1.27), (0.63, 0.57), (59.54, 1.46)),
    (3, "centralized"): ((67.94, 3.34), (142.12, 5.48), (0.20, 1.02), (0.06, 0.30), (61.71, 0.56)),
    (3, "fixed"): ((14.50, 3.87), (58.44, 0.81), (12.48, 58.77), (0.62, 1.23), (78.32, 11.07)),
    (3, "dronefl"): ((4.14, 2.21), (55.76, 0.65), (12.02, 57.50), (0.54, 1.20), (72.13, 4.70)),
}


def run_table1(
    base: TrackConfig,
    cases: tuple[int, ...] = (1, 2, 3),
    methods: tuple[str, ...] = TRACK_METHODS,
    seeds: tuple[int, ...] = (0, 1, 2),
) -> list[dict]:
    """Run (or reuse) every episode; write ``table1.md``, ``table1.csv`` and ``table1.png``."""
    out = Path(base.out)
    rows = []
    for case in cases:
        for method in methods:
            for seed in seeds:
                folder = out / f"case{case}" / method / f"seed{seed}"
                done = folder / "metrics.json"
                if done.is_file():
                    metrics = json.loads(done.read_text())
                else:
                    config = replace(base, case=case, method=method, seed=seed, out=folder)
                    metrics = run_episode(config)
                rows.append(
                    {
                        "case": case,
                        "method": method,
                        "seed": seed,
                        **{m: metrics[m] for m in (*METRICS, "wall_seconds")},
                    }
                )
    atomic_write_text(out / "table1.md", table1_markdown(rows))
    atomic_write_text(out / "table1.csv", _csv(rows))
    from dronefl.report.tracking import plot_table1_bars

    plot_table1_bars(rows, out / "table1.png")
    return rows


def summarize(rows: list[dict], case: int, method: str) -> dict[str, tuple[float, float]]:
    """Mean and std over seeds of each metric of one (case, method)."""
    sel = [r for r in rows if r["case"] == case and r["method"] == method]
    return {
        m: (float(np.mean([r[m] for r in sel])), float(np.std([r[m] for r in sel])))
        for m in METRICS
    }


def table1_markdown(rows: list[dict]) -> str:
    """Table I as markdown: ours (mean ± std over seeds) beside the paper's figures, and
    DroneFL's change against fixed distributed."""
    lines = [
        "| case | method | pred. error (m²) | track. distance (m²) | uncertainty (Tr P) "
        "| speed change (m/s) | total cost | paper: pred. error / track. distance |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for case in sorted({r["case"] for r in rows}):
        for method in TRACK_METHODS:
            if not any(r["case"] == case and r["method"] == method for r in rows):
                continue
            stats = summarize(rows, case, method)
            cells = " | ".join(f"{m:.2f} ± {s:.2f}" for m, s in stats.values())
            paper = PAPER.get((case, method))
            ref = f"{paper[0][0]:.2f} / {paper[1][0]:.2f}" if paper else "–"
            n = sum(1 for r in rows if r["case"] == case and r["method"] == method)
            lines.append(f"| {case} | {method} (n={n}) | {cells} | {ref} |")
    lines.append("")
    for case in sorted({r["case"] for r in rows}):
        methods = {r["method"] for r in rows if r["case"] == case}
        if {"fixed", "dronefl"} <= methods:
            ours, fixed = summarize(rows, case, "dronefl"), summarize(rows, case, "fixed")
            pe = 100 * (ours["prediction_error"][0] / fixed["prediction_error"][0] - 1)
            td = 100 * (ours["tracking_distance"][0] / fixed["tracking_distance"][0] - 1)
            lines.append(
                f"Case {case}: DroneFL vs fixed distributed: prediction error {pe:+.1f} %, "
                f"tracking distance {td:+.1f} % (paper: -6 % to -83 % and -0.4 % to -4.6 %)."
            )
    return "\n".join(lines) + "\n"


def _csv(rows: list[dict]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue()
