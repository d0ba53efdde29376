"""Compare closed-loop variants seed by seed: one folder of episodes per variant.

Each ``LABEL=FOLDER`` names a folder of ``seed<K>/metrics.json`` episodes (what ``dronefl
table1`` writes under ``<out>/<scenario>/<method>/`` or ``dronefl track`` per seed), all of one
scenario. Prints mean ± std over the seeds every variant flew and each variant's change against
the first, and plots every seed's prediction error, tracking distance and fused-track error
(m²). Run it, for instance, on a ``table1`` run with and one without ``--deshrink-labels``:

    python examples/compare_runs.py --out runs/compare.png \\
        fixed=runs/t/case2/fixed DroneFL=runs/t/case2/dronefl \\
        "DroneFL, de-shrunk=runs/t_dl/case2/dronefl"
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from dronefl.report.topdown import save_figure
from dronefl.results.episode import EpisodeMetrics

#: The compared columns of ``EpisodeMetrics.tracking``, with their axis labels.
COLUMNS: dict[str, str] = {
    "prediction_error": "prediction error (m²)",
    "tracking_distance": "tracking distance (m²)",
    "tracking_error": "fused-track error (m²)",
}


def load_variant(folder: Path) -> dict[int, EpisodeMetrics]:
    """Every finished episode in ``folder`` by seed (``FileNotFoundError`` when none)."""
    episodes = {}
    for path in sorted(folder.glob("seed*/metrics.json")):
        episode = EpisodeMetrics.load(path)
        episodes[episode.seed] = episode
    if not episodes:
        raise FileNotFoundError(f"{folder}: no seed*/metrics.json")
    return episodes


def compare(variants: dict[str, dict[int, EpisodeMetrics]]) -> tuple[str, list[int]]:
    """A markdown table of mean ± std (population std, as ``table1``) over the seeds every
    variant flew, each variant's change of the mean against the first; and those seeds."""
    seeds = sorted(set.intersection(*(set(v) for v in variants.values())))
    if not seeds:
        raise ValueError("the variants share no seed")
    scenarios = {e.scenario for v in variants.values() for e in v.values()}
    if len(scenarios) > 1:
        raise ValueError(f"the variants mix scenarios: {', '.join(sorted(scenarios))}")
    first = None  # the first variant's means
    lines = [
        f"| {scenarios.pop()}, seeds {' '.join(map(str, seeds))} | "
        + " | ".join(COLUMNS.values()) + " |",
        "|---" * (len(COLUMNS) + 1) + "|",
    ]  # fmt: skip
    for label, episodes in variants.items():
        values = {c: [getattr(episodes[s].tracking, c) for s in seeds] for c in COLUMNS}
        means = {c: float(np.mean(v)) for c, v in values.items()}
        cells = [f"{means[c]:.2f} ± {np.std(v):.2f}" for c, v in values.items()]
        if first is None:
            first = means
        else:
            cells = [
                f"{cell} ({100 * (means[c] / first[c] - 1):+.1f} %)"
                for cell, c in zip(cells, COLUMNS, strict=True)
            ]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n", seeds


def plot(variants: dict[str, dict[int, EpisodeMetrics]], seeds: list[int], path: Path) -> Path:
    """Every seed's value of each of :data:`COLUMNS`, one marker per variant (the axes do
    not start at 0: the differences are a few per cent)."""
    fig, axes = plt.subplots(1, len(COLUMNS), figsize=(4.2 * len(COLUMNS), 3.6))
    x = np.arange(len(seeds))
    width = 0.8 / len(variants)
    for ax, (column, label) in zip(axes, COLUMNS.items(), strict=True):
        for k, (name, episodes) in enumerate(variants.items()):
            values = [getattr(episodes[s].tracking, column) for s in seeds]
            offset = (k - (len(variants) - 1) / 2) * width
            ax.plot(x + offset, values, "o", markersize=7, label=name)
        ax.set_xticks(x, [f"seed {s}" for s in seeds])
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
    fig.legend(*axes[0].get_legend_handles_labels(), loc="upper center", ncol=len(variants))
    fig.tight_layout(rect=(0, 0, 1, 0.9))  # the legend above the axes, over no marker
    return save_figure(fig, path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("variants", nargs="+", help="LABEL=FOLDER of seed<K>/metrics.json")
    parser.add_argument("--out", type=Path, default=Path("runs/compare.png"), help="plot path")
    args = parser.parse_args()
    variants = {}
    for spec in args.variants:
        label, sep, folder = spec.rpartition("=")  # a label may hold "=", a folder not
        if not sep or not label or not folder:
            parser.error(f"{spec!r}: expected LABEL=FOLDER")
        try:
            variants[label] = load_variant(Path(folder))
        except FileNotFoundError as error:
            parser.error(str(error))
    try:
        table, seeds = compare(variants)
    except ValueError as error:
        parser.error(str(error))
    print(table)
    print(f"wrote {plot(variants, seeds, args.out)}")


if __name__ == "__main__":
    main()
