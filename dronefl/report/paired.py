"""Paired comparison of two methods over the seeds both ran: offline FL per drone
(``dronefl fl-compare``), closed-loop Table I per scenario (``dronefl table1-compare``).

Two methods run with the same seed share its recording or episode (targets, altitudes, test
windows, vehicles' paths), so their per-seed values move together; the seed-to-seed spread of
either mean hides differences that the paired differences show (or shows that there are none
to see). Per compared item ``k`` (a drone, a scenario), over the seeds ``s`` both ran:

    d_s = v_A(k, s) - v_B(k, s)                         (the metric's unit, e.g. m^2)
    mean d = (1/n) sum_s d_s,   s.e. = std(d, ddof=1) / sqrt(n)
    t = mean d / s.e. with n - 1 degrees of freedom (scipy.stats.ttest_rel), two-sided p

With five seeds the p-value only says whether a difference stands out of the seed noise at
all; ``wins`` counts the seeds on which A's value is strictly lower (lower is better for every
metric compared here).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy import stats

if TYPE_CHECKING:  # fl_offline's table uses this module
    from dronefl.results.fl import MethodResult


@dataclass(frozen=True)
class PairedRow:
    """One item's paired comparison of methods A and B (values in the metric's unit)."""

    name: str
    seeds: tuple[int, ...]
    mean_a: float
    mean_b: float
    mean_difference: float
    standard_error: float
    wins: int
    p_value: float

    @property
    def ratio(self) -> float:
        """``mean_a / mean_b``: below 1 where A is lower on the mean over the seeds."""
        return self.mean_a / self.mean_b


def paired_row(name: str, a: dict[int, float], b: dict[int, float]) -> PairedRow:
    """The paired comparison of ``a`` and ``b`` (value by seed) over the seeds both hold.

    Raises ``ValueError`` if they share fewer than two seeds."""
    seeds = sorted(set(a) & set(b))
    if len(seeds) < 2:
        raise ValueError(
            f"{name}: the two methods share {len(seeds)} seed(s) ({seeds}); a paired "
            "comparison needs at least two"
        )
    x = np.array([a[s] for s in seeds])
    y = np.array([b[s] for s in seeds])
    d = x - y
    p_value = float(stats.ttest_rel(x, y).pvalue) if np.any(d != d[0]) else float("nan")
    return PairedRow(
        name=name,
        seeds=tuple(seeds),
        mean_a=float(x.mean()),
        mean_b=float(y.mean()),
        mean_difference=float(d.mean()),
        standard_error=float(d.std(ddof=1) / np.sqrt(len(d))),
        wins=int(np.sum(x < y)),
        p_value=p_value,
    )


def paired_comparison(a: MethodResult, b: MethodResult) -> list[PairedRow]:
    """Per drone, the final test MSE (m^2) of ``a`` against ``b`` over the seeds both ran.

    Raises ``ValueError`` if they share fewer than two seeds or their drones differ."""
    if a.drones != b.drones:
        raise ValueError(f"{a.method} has drones {a.drones}, {b.method} has {b.drones}")
    return [
        paired_row(
            str(drone),
            {r.seed: r.final_test_mse_per_drone[drone] for r in a.seeds},
            {r.seed: r.final_test_mse_per_drone[drone] for r in b.seeds},
        )
        for drone in a.drones
    ]


def table1_comparison(path: Path, a: str, b: str, metric: str) -> list[PairedRow]:
    """Per scenario of a ``table1.csv``, ``metric`` of method ``a`` against ``b`` over the
    seeds both flew. Raises ``ValueError`` naming the file for a missing column or method."""
    with Path(path).open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    if not rows or metric not in rows[0]:
        have = ", ".join(
            k for k in (rows[0] if rows else {}) if k not in {"scenario", "method", "seed"}
        )
        raise ValueError(f"{path}: no column {metric!r} (it has {have or 'no rows'})")
    values: dict[tuple[str, str], dict[int, float]] = {}
    for row in rows:
        values.setdefault((row["scenario"], row["method"]), {})[int(row["seed"])] = float(
            row[metric]
        )
    scenarios = list(dict.fromkeys(row["scenario"] for row in rows))
    for method in (a, b):
        if not any(m == method for _, m in values):
            methods = sorted({m for _, m in values})
            raise ValueError(f"{path}: no method {method!r} (it has {methods})")
    return [
        paired_row(scenario, values[(scenario, a)], values[(scenario, b)])
        for scenario in scenarios
        if (scenario, a) in values and (scenario, b) in values
    ]


def paired_markdown(
    rows: list[PairedRow], label_a: str, label_b: str, item: str = "drone", unit: str = "m²"
) -> str:
    """The rows as a Markdown table, one line per compared ``item``."""
    n = len(rows[0].seeds)
    lines = [
        f"| {item} | {label_a} ({unit}) | {label_b} ({unit}) | ratio | difference ± s.e. "
        f"({unit}) | {label_a} lower on | p (paired t, {n - 1} dof) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.name} | {r.mean_a:.3f} | {r.mean_b:.3f} | {r.ratio:.2f} | "
            f"{r.mean_difference:+.3f} ± {r.standard_error:.3f} | {r.wins} of {len(r.seeds)} "
            f"seeds | {r.p_value:.2g} |"
        )
    return "\n".join(lines)
