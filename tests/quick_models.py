"""Quickly trained stand-ins for the closed loop's pretrained models, planted where the closed
loop looks for them (``conftest.quick_pretrained`` builds them once per test run)."""

from __future__ import annotations

import shutil
from pathlib import Path

#: The named settings whose quick models :func:`quick_pretrained` caches.
QUICK_SETTINGS = ("recommended", "paper")


def quick_gaps() -> tuple[float, ...]:
    """The pretraining detection gaps the quick models stand in for: every candidate of
    ``detection_gaps = "auto"`` (0 is the paper setting's)."""
    from dronefl.experiments.gap_choice import GAP_CANDIDATES

    return GAP_CANDIDATES


def stand_in_gap_choice(spec, folder: Path) -> None:
    """Record ``detection_gaps = "auto"``'s choice for ``spec`` in ``folder`` as 0 (the quick
    models are one model for every candidate; no validation flight is flown for them)."""
    from dronefl.experiments.gap_choice import GapChoice

    GapChoice(0.0, {}).save(GapChoice.path(spec, folder, quick_gaps()))


def quick_specs(scenario):
    """``(setting name, PretrainSpec)`` of the DroneFL model of every quick setting for
    ``scenario`` (a :class:`~dronefl.config.Scenario` or a name), at every candidate's
    detection gaps."""
    from dronefl.config import load_scenario
    from dronefl.experiments.pretrain import PretrainSpec
    from dronefl.settings import Setting

    scenario = load_scenario(scenario) if isinstance(scenario, str) else scenario
    for name in QUICK_SETTINGS:
        for gaps in quick_gaps():
            yield name, PretrainSpec(scenario, Setting.load(name), "dronefl", detection_gaps=gaps)


def plant_quick_models(quick: Path, scenario, folder: Path) -> Path:
    """Copy the quick Case 1 models of ``quick`` into ``folder`` as ``scenario``'s (a
    :class:`~dronefl.config.Scenario` or a name)."""
    from dronefl.fl.checkpoint import Checkpoint, load_checkpoint, save_checkpoint

    for (_, case1), (_, other) in zip(quick_specs("case1"), quick_specs(scenario), strict=True):
        source, target = case1.settings(quick), other.settings(folder)
        state = load_checkpoint(source.checkpoint_path, source.history_path, "dronefl").state
        checkpoint = Checkpoint("dronefl", target.rounds, state, [])
        save_checkpoint(target.checkpoint_path, target.history_path, checkpoint)
        stand_in_gap_choice(other, folder)
    return folder


def train_quick_models(folder: Path) -> None:
    """Train the quick models into ``folder`` (see ``conftest.quick_pretrained``)."""
    import torch

    from dronefl.config import load_scenario
    from dronefl.experiments.simulate import simulate
    from dronefl.fl.checkpoint import Checkpoint, save_checkpoint
    from dronefl.logs import load_run
    from dronefl.models.model import build_model
    from dronefl.models.train import TrainConfig, train_local
    from dronefl.models.windows import WindowSet, WindowSpec, build_windows, ground_truth_labels

    if folder.exists():  # a run that died while building it
        shutil.rmtree(folder)
    data = folder / "data"
    simulate(
        load_scenario("case1"),
        environment="crop_field",
        duration=120.0,
        seed=5,
        out=data,
        progress=False,
        plot=False,
    )
    logs, truth = load_run(data)
    windows_spec = WindowSpec(10, 1, relative=True, stride=2)
    windows = WindowSet.concat(
        [build_windows(log, ground_truth_labels(log, truth), windows_spec) for log in logs.values()]
    )
    torch.set_num_threads(1)
    models = {}
    for name, spec in quick_specs("case1"):  # one stand-in for the pretrainings at any gaps
        if name not in models:
            models[name] = build_model(spec.model, seed=0)
            train_local(models[name], windows, TrainConfig(epochs=20, batch_size=32, seed=0))
        settings = spec.settings(folder)
        save_checkpoint(
            settings.checkpoint_path,
            settings.history_path,
            Checkpoint("dronefl", settings.rounds, models[name].state_dict(), []),
        )
        stand_in_gap_choice(spec, folder)
