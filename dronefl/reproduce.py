"""``dronefl reproduce``: every paper artefact in one command, exactly as the README reports it.

Each artefact is a list of runs of the existing experiments (offline FL, Table I's episodes,
the benchmarks) with the settings the README's tables were measured with, written under
``<out>/<artefact>/`` and resumed from what is there (finished runs are reused). Then the
artefact's summary (``<out>/<artefact>/<artefact>.md``) puts ours beside the paper's:

* ``fig4``: the altitude motivation study (paper Fig. 4): drone 1's test MSE with a partner
  drone at its own altitude or 10 m lower, with and without the altitude conditioning;
* ``fig5``: offline FL (paper Fig. 5) in every case, each case's DroneFL trained as its own
  tuning recordings chose (:data:`FIG5_RUNS`), beside pooled training, each drone alone,
  DroneFL without AdaIN and the paper's FL baselines in the paper's setting;
* ``table1``: Table I (closed loop, orchard, 600 s) in the recommended setting and in the
  paper's system as written;
* ``table2``: Table II (efficiency), the benchmarks (:mod:`dronefl.bench`).

``quick`` shrinks every size (one seed, a few rounds, short recordings and episodes, a short
pretraining) into a smoke run of minutes; its numbers are not the README's.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from dronefl.config import load_scenario
from dronefl.experiments.fl_offline import OfflineConfig, run_altitude_study, run_fl_offline
from dronefl.experiments.table1 import run_table1
from dronefl.experiments.track import TrackConfig
from dronefl.io import atomic_write_text
from dronefl.report.fl_plots import plot_fig5
from dronefl.results.fl import OfflineResults
from dronefl.settings import Setting

#: The artefacts, in the order ``all`` runs them.
ARTEFACTS: tuple[str, ...] = ("fig4", "fig5", "table1", "table2")
#: The paper's cases.
CASES: tuple[str, ...] = ("case1", "case2", "case3")
#: Case 1's DroneFL trains with FedAvg (SGD): on its tuning recordings every SCAFFOLD variant
#: ended worse.
FEDAVG_SGD = ("training.drift_correction=none",)
#: Adam, as the pooled references train best with it (metric box sizes, batch 64).
ADAM = ("training.optimizer=adam", "training.lr=1e-3", "training.drift_correction=none")
#: The lr x 0.1 in the last fifth of the rounds (Cases 2-3's references).
STEP = ("training.lr_step_at=0.8",)
#: Cases 2-3's DroneFL: SCAFFOLD at twice the lr, with the step.
STEP_LR6 = ("training.lr=6e-4", "training.lr_step_at=0.8")


@dataclass(frozen=True)
class FlRun:
    """One ``fl-offline`` run of Fig. 5: ``methods`` of ``case`` trained as the named
    ``setting`` with ``overrides`` says, in ``<fig5>/<case>/<folder>``."""

    case: str
    folder: str
    setting: str
    overrides: tuple[str, ...]
    methods: tuple[str, ...]


#: Fig. 5 as the README reports it (per case: which training, which methods).
FIG5_RUNS: tuple[FlRun, ...] = (
    FlRun("case1", "dronefl", "recommended", FEDAVG_SGD, ("dronefl", "local", "dronefl-no-adain")),
    FlRun("case1", "pooled", "recommended", ADAM, ("centralized-small", "centralized")),
    *(
        run
        for case in ("case2", "case3")
        for run in (
            FlRun(case, "dronefl", "recommended", STEP_LR6, ("dronefl", "dronefl-no-adain")),
            FlRun(case, "references", "recommended", STEP, ("local", "centralized-small")),
            FlRun(case, "large", "recommended", ADAM, ("centralized",)),
        )
    ),
    *(FlRun(case, "baselines", "paper", (), ("fedavg", "fedprox", "fedper")) for case in CASES),
)


@dataclass(frozen=True)
class Scale:
    """How big a reproduction is: ``seeds``, offline FL ``rounds`` on ``recording`` s of crop
    field, closed-loop ``episode`` s, ``pretraining`` overrides of every closed-loop setting
    (none at full size) and the benchmarks' ``quick`` sizes."""

    seeds: tuple[int, ...]
    rounds: int
    recording: float
    episode: float
    pretraining: tuple[str, ...]
    quick: bool


FULL = Scale((0, 1, 2, 3, 4), 50, 600.0, 600.0, (), quick=False)
QUICK = Scale(
    (0,), 2, 60.0, 30.0,
    ("pretraining.rounds=2", "pretraining.seconds=60", "pretraining.detection_gaps=0"),
    quick=True,
)  # fmt: skip


def reproduce(
    artefact: str, out: Path, quick: bool = False, pretrained: Path | None = None
) -> Path:
    """Run ``artefact`` (one of :data:`ARTEFACTS`, or ``all``) into ``out``, reusing finished
    runs there; returns the summary file written (``all``: the last one)."""
    if artefact not in (*ARTEFACTS, "all"):
        raise ValueError(f"ARTEFACT: {artefact!r} is not one of {', '.join(ARTEFACTS)}, all")
    scale = QUICK if quick else FULL
    cache = Path(pretrained) if pretrained is not None else out / "pretrained"
    runs: dict[str, Callable[[], Path]] = {
        "fig4": lambda: _fig4(out / "fig4", scale),
        "fig5": lambda: _fig5(out / "fig5", scale),
        "table1": lambda: _table1(out / "table1", scale, cache),
        "table2": lambda: _table2(out / "table2", scale, cache),
    }
    written = out
    for name in ARTEFACTS if artefact == "all" else (artefact,):
        written = runs[name]()
    return written


def _fig4(out: Path, scale: Scale) -> Path:
    study = run_altitude_study(
        out, "case1", scale.rounds, scale.seeds, methods=("dronefl-no-adain", "dronefl"),
        setting=Setting.load("recommended", FEDAVG_SGD), resume=True,
    )  # fmt: skip
    lines = [
        "# Fig. 4: drone 1's test MSE with a partner drone at its own altitude or 10 m lower",
        "",
        "Paper: without the altitude conditioning the loss fluctuates when the partner flies "
        "lower (a plot). Ours (case1, FedAvg with SGD, "
        f"{scale.rounds} rounds, seeds {' '.join(map(str, scale.seeds))}):",
        "",
        "| run | drone 1's final test MSE (m²) |",
        "|---|---|",
        *(
            f"| {name} | {curve['final']:.3g} ± {curve['final_std']:.2g} |"
            for name, curve in study["curves"].items()
        ),
        "",
        "![Fig. 4](fig4_altitude.png)",
    ]
    return atomic_write_text(out / "fig4.md", "\n".join(lines) + "\n")


def _fig5(out: Path, scale: Scale) -> Path:
    by_case: dict[str, list[OfflineResults]] = {case: [] for case in CASES}
    for run in FIG5_RUNS:
        config = OfflineConfig(
            run.case, out / run.case / run.folder, Setting.load(run.setting, run.overrides),
            scale.rounds, scale.seeds, scale.recording, methods=run.methods, resume=True,
        )  # fmt: skip
        by_case[run.case].append(run_fl_offline(config))
    lines = [
        "# Fig. 5: final test MSE (m²) after the last round, crop field",
        "",
        f"Seeds {' '.join(map(str, scale.seeds))}, {scale.rounds} rounds, mean ± std over "
        "seeds. Paper: DroneFL approaches centralized training and is 47-96 % below FedAvg, "
        "FedProx and FedPer.",
        "",
        "| case | DroneFL | pooled (centralized-small) | DroneFL / pooled | local | without "
        "AdaIN | best of FedAvg / FedProx / FedPer |",
        "|---|---|---|---|---|---|---|",
    ]
    for case, results in by_case.items():
        blocks = {m: b for r in results for m, b in r.methods.items()}
        curves = {m: b.curve for m, b in blocks.items()}
        plot_fig5(
            curves, f"{case}, seeds {' '.join(map(str, scale.seeds))}", out / f"fig5_{case}.png"
        )
        final = {m: b.final_test_mse for m, b in blocks.items()}
        best = min(final[m] for m in ("fedavg", "fedprox", "fedper"))
        lines.append(
            f"| {case} | {_mean_std(blocks['dronefl'])} | {_mean_std(blocks['centralized-small'])} "
            f"| {final['dronefl'] / final['centralized-small']:.2f}x | {final['local']:.3g} "
            f"| {final['dronefl-no-adain']:.3g} | {best:.4g} |"
        )
    lines += ["", *(f"![{case}](fig5_{case}.png)" for case in CASES)]
    return atomic_write_text(out / "fig5.md", "\n".join(lines) + "\n")


def _mean_std(block) -> str:
    return f"{block.final_test_mse:.3g} ± {block.final_test_mse_std:.2g}"


def _table1(out: Path, scale: Scale, cache: Path) -> Path:
    scenarios = tuple(load_scenario(case) for case in CASES)
    summaries = []
    for name in ("recommended", "paper"):
        base = TrackConfig(
            scenarios[0], out / name, Setting.load(name, scale.pretraining),
            duration=scale.episode, pretrained=cache, animate=False,
        )  # fmt: skip
        run_table1(base, scenarios, seeds=scale.seeds)
        summaries += [f"## {name}", "", (out / name / "table1.md").read_text(), ""]
        summaries += [f"![Table I, {name}]({name}/table1.png)", ""]
    text = "# Table I: closed loop, orchard\n\n" + "\n".join(summaries)
    return atomic_write_text(out / "table1.md", text)


def _table2(out: Path, scale: Scale, cache: Path) -> Path:
    from dronefl.bench.run import run_bench

    setting = Setting.load("recommended", scale.pretraining)
    run_bench(
        out, quick=scale.quick, pretrained=cache, scenario=load_scenario("case3"), setting=setting
    )
    return out / "bench.md"
