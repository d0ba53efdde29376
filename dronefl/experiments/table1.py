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
from pathlib import Path

from dronefl.config import Scenario
from dronefl.experiments.loop_checkpoint import check_same_episode
from dronefl.experiments.track import TrackConfig, run_episode
from dronefl.fl.checkpoint import CheckpointError
from dronefl.io import atomic_write_text
from dronefl.results.episode import EpisodeMetrics
from dronefl.results.table1 import row_name, summarize
from dronefl.serialize import ResultError
from dronefl.settings import LABEL_SOURCES

#: Table I's methods on each detector's path: the paper's three; on rendered frames its
#: centralized baseline is its own, the image model (``centralized-image``).
TABLE1_METHODS: dict[str, tuple[str, ...]] = {
    "projection": ("centralized", "fixed", "dronefl"),
    "yolo": ("centralized-image", "fixed", "dronefl"),
}


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
    own = base.setting.learning.labels
    runs = [(method, base.setting, method) for method in methods]
    if label_ablation:
        runs += [
            (
                "dronefl",
                base.setting.with_values(learning={"labels": labels}),
                f"dronefl-labels-{labels}",
            )
            for labels in LABEL_SOURCES
            if labels != own
        ]
    return [
        dataclasses.replace(
            base,
            scenario=scenario,
            method=method,
            setting=setting,
            seed=seed,
            out=out / scenario.name / folder / f"seed{seed}",
        )  # fmt: skip
        for scenario in scenarios
        for method, setting, folder in runs
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
    rows = summarize(episodes, base.setting.learning.labels)
    from dronefl.report.tables import table1_csv, table1_markdown
    from dronefl.report.tracking import plot_table1_bars

    atomic_write_text(out / "table1.md", table1_markdown(rows))
    names = [row_name(e, base.setting.learning.labels) for e in episodes]
    atomic_write_text(out / "table1.csv", table1_csv(episodes, names))
    plot_table1_bars(rows, out / "table1.png")
    return episodes


def _finished(config: TrackConfig) -> EpisodeMetrics | None:
    """The finished episode of exactly ``config`` (:meth:`TrackConfig.identity`), or None
    (missing, corrupt or of another episode: it is flown again)."""
    path = Path(config.out) / "metrics.json"
    if not path.is_file():
        return None
    try:
        metrics = EpisodeMetrics.load(path)
        check_same_episode(path, metrics.config, config.identity())
    except (ResultError, CheckpointError):
        return None
    return metrics
