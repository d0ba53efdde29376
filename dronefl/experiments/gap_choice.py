"""``pretraining.detection_gaps = "auto"``: the detection-gap probability of a scenario's crop-field
pretraining, chosen on an orchard validation recording.

The crop field hardly hides a target; the orchard's trees do, and a model pretrained on
windows as recorded predicts badly from a window with gaps (Case 2: 0.54-14.5 m² one step
ahead from windows of 9 ... 1 detections of 10, against 0.24 from full ones).
:attr:`~dronefl.experiments.pretrain.PretrainSpec.detection_gaps` cuts gaps into the
pretraining windows; whether a scenario's models gain by it depends on how often its targets
are hidden (docs/rules/pretrain_gaps.md: Case 1's lose 2 %, Case 2's gain 91 %), so
:func:`choose_detection_gaps` pretrains each candidate and keeps the best on a recording the
episodes never fly. Kept apart from :mod:`dronefl.experiments.pretrain`, whose source is part
of the pretraining cache key.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dronefl.experiments.pretrain import (
    RECORDING_CODE,
    PretrainSpec,
    _digest,
    package_digest,
    pretrained_state,
)
from dronefl.experiments.simulate import simulate
from dronefl.io import atomic_write_json
from dronefl.logs import load_run
from dronefl.models.model import build_model
from dronefl.models.windows import WindowSet, build_windows, ground_truth_labels
from dronefl.serialize import ResultError
from dronefl.settings import AUTO

#: ``detection_gaps = "auto"``: the detection-gap probabilities a scenario's pretraining chooses
#: from (0.3: the best of 0.15 / 0.3 / 0.5 on Case 2's tuning recording, docs/rules/
#: pretrain_gaps.md), on an orchard validation recording with seed :data:`GAP_VALIDATION_SEED`
#: (never an episode's), the smaller unless a larger one is :data:`GAP_TIE` better.
GAP_CANDIDATES: tuple[float, ...] = (0.0, 0.3)
GAP_VALIDATION_SEED = 1001
GAP_TIE = 0.02


def validation_dir(spec: PretrainSpec, folder: Path) -> Path:
    """Where the orchard validation recording of ``spec``'s scenario is cached (``duration``
    s under the scripted pilot, seed :data:`GAP_VALIDATION_SEED`)."""
    key = _digest(
        [spec.scenario.content_hash, spec.duration, GAP_VALIDATION_SEED,
         package_digest(RECORDING_CODE)]
    )  # fmt: skip
    return Path(folder) / spec.scenario.name / f"orchard-{key}"


def window_set(run: Path, spec: PretrainSpec, folder: Path) -> WindowSet:
    """Every window (L_p -> 1, stride 1, ground-truth labels) of every drone of the recorded
    run folder ``run``, cut as ``spec``'s model reads them."""
    windows = dataclasses.replace(
        spec.settings(folder).windows, future_steps=1, stride=1, train_fraction=1.0
    )
    logs, truth = load_run(run)
    return WindowSet.concat(
        [build_windows(log, ground_truth_labels(log, truth), windows) for log in logs.values()]
    )


@torch.no_grad()
def window_errors(
    state: dict[str, torch.Tensor], spec: PretrainSpec, data: WindowSet
) -> np.ndarray:
    """Each window's one-step squared error (m², the mean of the two axes) of ``spec``'s
    model with weights ``state``."""
    model = build_model(spec.model)
    model.load_state_dict(state)
    model.eval()
    prediction = model(torch.from_numpy(data.features), torch.from_numpy(data.altitude))
    return ((prediction.numpy() - data.labels) ** 2).mean(axis=(1, 2))


@dataclass(frozen=True)
class GapChoice:
    """The detection-gap probability ``chosen`` for a scenario's pretraining, with each
    candidate's one-step MSE (m²) over every window of the orchard validation recording."""

    chosen: float
    mse: dict[float, float]

    @staticmethod
    def path(spec: PretrainSpec, folder: Path, candidates: tuple[float, ...]) -> Path:
        """Where the choice for ``spec`` (its ``detection_gaps`` ignored) is cached: keyed by
        every candidate's pretraining and the validation recording."""
        runs = [
            Path(
                dataclasses.replace(spec, kind="dronefl", detection_gaps=p).settings(folder).out_dir
            ).name
            for p in candidates
        ]
        key = _digest([runs, validation_dir(spec, folder).name, GAP_TIE])
        return Path(folder) / spec.scenario.name / f"gaps-{key}.json"

    def save(self, path: Path) -> Path:
        """Write the choice atomically."""
        return atomic_write_json(
            path, {"chosen": self.chosen, "mse": {str(p): v for p, v in self.mse.items()}}
        )

    @classmethod
    def load(cls, path: Path) -> GapChoice:
        """The choice saved in ``path`` (:class:`~dronefl.serialize.ResultError` naming the file
        when it is not one)."""
        try:
            raw = json.loads(Path(path).read_text())
            return cls(float(raw["chosen"]), {float(p): float(v) for p, v in raw["mse"].items()})
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise ResultError(
                f"{path}: not a detection-gap choice ({exc}); delete it to choose again"
            ) from None


def choose_detection_gaps(
    spec: PretrainSpec,
    folder: Path,
    candidates: tuple[float, ...] = GAP_CANDIDATES,
    progress: bool = True,
) -> GapChoice:
    """``detection_gaps = "auto"``: pretrain ``spec``'s DroneFL model with each of ``candidates``
    (ascending), score each on every window of an orchard validation recording of the
    scenario (:func:`validation_dir`; ground truth, as a calibration flight with surveyed
    vehicles would give), and keep the smallest probability that no larger one beats by more
    than :data:`GAP_TIE`. The orchard hides targets; whether a scenario's models gain from
    having seen gaps depends on how often its targets are hidden and on the model (Case 1's
    lose 2 %, Case 2's gain 91 %: docs/rules/pretrain_gaps.md). Cached per scenario, code and
    setting (:meth:`GapChoice.path`)."""
    if list(candidates) != sorted(set(candidates)) or not candidates:
        raise ValueError(f"gap candidates must be ascending and distinct, got {candidates}")
    cached = GapChoice.path(spec, folder, candidates)
    if cached.is_file():
        return GapChoice.load(cached)
    specs = [dataclasses.replace(spec, kind="dronefl", detection_gaps=p) for p in candidates]
    states = [pretrained_state(s, folder, progress) for s in specs]
    run = validation_dir(spec, folder)
    if not (run / "ground_truth.npz").is_file():
        simulate(spec.scenario, environment="orchard", duration=spec.duration,
                 seed=GAP_VALIDATION_SEED, out=run, progress=progress, plot=False)  # fmt: skip
    data = window_set(run, specs[0], folder)
    mse = {
        p: float(window_errors(w, s, data).mean())
        for p, w, s in zip(candidates, states, specs, strict=True)
    }
    chosen = candidates[0]
    for p in candidates[1:]:
        if mse[p] < (1.0 - GAP_TIE) * mse[chosen]:
            chosen = p
    choice = GapChoice(chosen, mse)
    choice.save(cached)
    return choice


def resolve_gaps(spec: PretrainSpec, folder: Path, progress: bool = True) -> PretrainSpec:
    """``spec`` with the detection-gap probability its setting asks for
    (``pretraining.detection_gaps``): a number as it is, ``auto`` the scenario's choice
    (:func:`choose_detection_gaps`, pretraining the candidates when they are not cached). The
    image model reads frames, not windows: its spec is returned as it is."""
    gaps = spec.setting.pretraining.detection_gaps
    if spec.kind == "image":
        return spec
    if gaps == AUTO:
        gaps = choose_detection_gaps(spec, folder, progress=progress).chosen
    return dataclasses.replace(spec, detection_gaps=float(gaps))
