"""Paired comparison of two federated methods over the seeds both ran (``dronefl fl-compare``).

Two methods trained on the same recording (same seed) share its targets, altitudes and test
windows, so their per-seed errors move together; the seed-to-seed spread of either mean hides
differences that the paired differences show (or shows that there are none to see). Per
drone ``k``, over the seeds ``s`` in both results:

    d_s = MSE_A(k, s) - MSE_B(k, s)                           (m^2)
    mean d = (1/n) sum_s d_s,   s.e. = std(d, ddof=1) / sqrt(n)
    t = mean d / s.e. with n - 1 degrees of freedom (scipy.stats.ttest_rel), two-sided p

With five seeds the p-value only says whether a difference stands out of the seed noise at
all; ``wins`` counts the seeds on which A's error is strictly lower.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from dronefl.experiments.fl_offline import MethodResult


@dataclass(frozen=True)
class PairedRow:
    """One drone's paired comparison of methods A and B (MSE in m^2)."""

    drone: int
    seeds: tuple[int, ...]
    mean_a: float
    mean_b: float
    mean_difference: float
    standard_error: float
    wins: int
    p_value: float

    @property
    def ratio(self) -> float:
        """``mean_a / mean_b``: below 1 where A is better on the mean over the seeds."""
        return self.mean_a / self.mean_b


def paired_comparison(a: MethodResult, b: MethodResult) -> list[PairedRow]:
    """Per drone of ``a``, the paired comparison with ``b`` over the seeds both ran.

    Raises ``ValueError`` if they share fewer than two seeds or their drones differ."""
    seeds = sorted({r.seed for r in a.seeds} & {r.seed for r in b.seeds})
    if len(seeds) < 2:
        raise ValueError(
            f"{a.method} and {b.method} share {len(seeds)} seed(s) ({seeds}); a paired "
            "comparison needs at least two"
        )
    if a.drones != b.drones:
        raise ValueError(f"{a.method} has drones {a.drones}, {b.method} has {b.drones}")
    rows = []
    for drone in a.drones:
        x = np.array([a.seed_result(s).final_test_mse_per_drone[drone] for s in seeds])  # type: ignore[union-attr]
        y = np.array([b.seed_result(s).final_test_mse_per_drone[drone] for s in seeds])  # type: ignore[union-attr]
        d = x - y
        p_value = float(stats.ttest_rel(x, y).pvalue) if np.any(d != d[0]) else float("nan")
        rows.append(
            PairedRow(
                drone=drone,
                seeds=tuple(seeds),
                mean_a=float(x.mean()),
                mean_b=float(y.mean()),
                mean_difference=float(d.mean()),
                standard_error=float(d.std(ddof=1) / np.sqrt(len(d))),
                wins=int(np.sum(x < y)),
                p_value=p_value,
            )
        )
    return rows


def paired_markdown(rows: list[PairedRow], label_a: str, label_b: str) -> str:
    """The rows as a Markdown table, one line per drone."""
    n = len(rows[0].seeds)
    lines = [
        f"| drone | {label_a} (m²) | {label_b} (m²) | ratio | difference ± s.e. (m²) | "
        f"{label_a} lower on | p (paired t, {n - 1} dof) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.drone} | {r.mean_a:.3f} | {r.mean_b:.3f} | {r.ratio:.2f} | "
            f"{r.mean_difference:+.3f} ± {r.standard_error:.3f} | {r.wins} of {n} seeds | "
            f"{r.p_value:.2f} |"
        )
    return "\n".join(lines)
