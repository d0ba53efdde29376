"""Table I: closed-loop tracking for scenarios x {centralized, fixed, DroneFL} x seeds.

The centralized baseline is the large box model on the projection detector's path and the
paper's image model on rendered frames (:data:`TABLE1_METHODS`).

Each episode writes its own folder ``<out>/<scenario>/<method>/seed<K>/``; a finished episode
(a ``metrics.json`` of the same scenario content and the same settings) is reused, so an
interrupted table resumes where it stopped. :func:`summarize` gives one :class:`Table1Row`
(mean ± std over seeds) per scenario and method; :mod:`dronefl.report` turns them into
markdown, CSV and a plot. With ``label_ablation`` DroneFL is flown again with each other
source of pseudo-labels (:data:`~dronefl.tracking.LABEL_SOURCES`), in
``<out>/<scenario>/dronefl-labels-<source>/``, as rows ``dronefl[labels=<source>]``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dronefl.config import Scenario
from dronefl.experiments.episode import EpisodeLog, EpisodeMetrics, tracking_metrics
from dronefl.experiments.track import NOT_SETTINGS, TrackConfig, run_episode
from dronefl.io import atomic_write_text
from dronefl.results import ResultError
from dronefl.tracking import LABEL_SOURCES

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
#: Table I's methods on each detector's path: the paper's three; on rendered frames its
#: centralized baseline is its own, the image model (``centralized-image``).
TABLE1_METHODS: dict[str, tuple[str, ...]] = {
    "projection": ("centralized", "fixed", "dronefl"),
    "yolo": ("centralized-image", "fixed", "dronefl"),
}


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


def episode_configs(
    base: TrackConfig,
    scenarios: tuple[Scenario, ...],
    methods: tuple[str, ...] | None = None,
    seeds: tuple[int, ...] = (0, 1, 2),
    label_ablation: bool = False,
) -> list[TrackConfig]:
    """Every episode of the table: ``base`` for each scenario x method (default:
    :data:`TABLE1_METHODS` of the detector) x seed, each in its folder
    ``<out>/<scenario>/<method>/seed<K>/``; with ``label_ablation``, after each scenario's,
    DroneFL with every other label source (``<out>/<scenario>/dronefl-labels-<source>/``).
    ``ValueError`` naming the option for a method that cannot fly these settings, or for
    ``--label-ablation`` without ``dronefl`` among the methods."""
    out = Path(base.out)
    methods = TABLE1_METHODS[base.detector] if methods is None else methods
    if label_ablation and "dronefl" not in methods:
        raise ValueError("--label-ablation: it flies DroneFL again; give dronefl in --methods")
    runs = [(method, base.labels, method) for method in methods]
    if label_ablation:
        runs += [
            ("dronefl", labels, f"dronefl-labels-{labels}")
            for labels in LABEL_SOURCES
            if labels != base.labels
        ]
    return [
        dataclasses.replace(
            base,
            scenario=scenario,
            method=method,
            labels=labels,
            seed=seed,
            out=out / scenario.name / folder / f"seed{seed}",
        )  # fmt: skip
        for scenario in scenarios
        for method, labels, folder in runs
        for seed in seeds
    ]


def run_table1(
    base: TrackConfig,
    scenarios: tuple[Scenario, ...],
    methods: tuple[str, ...] | None = None,
    seeds: tuple[int, ...] = (0, 1, 2),
    label_ablation: bool = False,
) -> list[EpisodeMetrics]:
    """Run (or reuse) every episode of :func:`episode_configs` (all checked before any work);
    write ``table1.md``, ``table1.csv`` and ``table1.png`` into ``base.out`` and return every
    episode's metrics."""
    out = Path(base.out)
    episodes = []
    for config in episode_configs(base, scenarios, methods, seeds, label_ablation):
        done = _finished(config)
        episodes.append(run_episode(config) if done is None else done)
    rows = summarize(episodes, base.labels)
    from dronefl.report.tables import table1_csv, table1_markdown
    from dronefl.report.tracking import plot_table1_bars

    atomic_write_text(out / "table1.md", table1_markdown(rows))
    names = [row_name(e, base.labels) for e in episodes]
    atomic_write_text(out / "table1.csv", table1_csv(episodes, names))
    plot_table1_bars(rows, out / "table1.png")
    return episodes


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


def _finished(config: TrackConfig) -> EpisodeMetrics | None:
    """The finished episode of exactly ``config`` (scenario content and every setting), or
    None (missing, corrupt or stale). One finished before ``sent_prediction_error`` was
    measured gets it from its ``episode.npz`` (the file is left as it is)."""
    path = Path(config.out) / "metrics.json"
    if not path.is_file():
        return None
    try:
        metrics = EpisodeMetrics.load(path)
    except ResultError:
        return None
    ran = {k: v for k, v in metrics.config.items() if k not in NOT_SETTINGS}
    same = metrics.scenario_hash == config.scenario.content_hash and ran == config.settings()
    if not same:
        return None
    if math.isnan(metrics.tracking.sent_prediction_error):
        try:
            log = EpisodeLog.load(path.parent / "episode.npz")
        except (OSError, ValueError):
            return metrics
        sent = tracking_metrics(log, config.scenario).sent_prediction_error
        metrics = dataclasses.replace(
            metrics, tracking=dataclasses.replace(metrics.tracking, sent_prediction_error=sent)
        )
    return metrics
