"""Table I's results: one row per (scenario, method) of closed-loop episodes, mean ± std over
seeds (:func:`summarize`), with the paper's columns and what the fusion gets and makes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronefl.results.episode import EpisodeMetrics

#: Table I's columns, in the paper's order.
METRICS: tuple[str, ...] = (
    "prediction_error", "tracking_distance", "uncertainty", "speed_change", "total_cost",
)  # fmt: skip
#: Beside them, what the fusion gets and makes (m^2): ``sent_prediction_error``, the prediction
#: error of the predictions sent to the cloud, and ``tracking_error``, the fused tracks' MSE.
FUSION_METRICS: tuple[str, ...] = ("sent_prediction_error", "tracking_error")
#: Multi-target set distances of the fused tracks (m), beside the paper's columns.
SET_METRICS: tuple[str, ...] = ("ospa", "gospa")
#: Every column a :class:`Table1Row` holds.
COLUMNS: tuple[str, ...] = METRICS + FUSION_METRICS + SET_METRICS


def episode_value(episode: EpisodeMetrics, column: str) -> float:
    """``column`` (one of :data:`COLUMNS`) of one episode."""
    source = episode.set_distances if column in SET_METRICS else episode.tracking
    return float(getattr(source, column))


@dataclass(frozen=True)
class Table1Row:
    """One (scenario, method) of Table I: ``mean`` and ``std`` over ``seeds`` of each of
    :data:`COLUMNS` (units as in :class:`TrackingMetrics` and :class:`SetDistances`) and the
    mean wall time (s)."""

    scenario: str
    method: str
    seeds: tuple[int, ...]
    mean: dict[str, float]
    std: dict[str, float]
    wall_seconds: float


def row_name(episode: EpisodeMetrics, base_labels: str | None = None) -> str:
    """The Table I row ``episode`` belongs to: its method, with ``[labels=<source>]`` when
    it learnt from other pseudo-labels than the table's ``base_labels`` (a label-ablation
    row; ``None``: never)."""
    if base_labels is None or episode.labels == base_labels:
        return episode.method
    return f"{episode.method}[labels={episode.labels}]"


def summarize(episodes: list[EpisodeMetrics], base_labels: str | None = None) -> list[Table1Row]:
    """Mean and std over seeds per (scenario, row), in the order first seen; the row is the
    method, and the label source where it is not ``base_labels`` (:func:`row_name`)."""
    groups: dict[tuple[str, str], list[EpisodeMetrics]] = {}
    for e in episodes:
        groups.setdefault((e.scenario, row_name(e, base_labels)), []).append(e)
    rows = []
    for (scenario, method), group in groups.items():
        values = {m: [episode_value(e, m) for e in group] for m in COLUMNS}
        rows.append(
            Table1Row(
                scenario=scenario,
                method=method,
                seeds=tuple(e.seed for e in group),
                mean={m: float(np.mean(v)) for m, v in values.items()},
                std={m: float(np.std(v)) for m, v in values.items()},
                wall_seconds=float(np.mean([e.wall_seconds for e in group])),
            )
        )
    return rows
