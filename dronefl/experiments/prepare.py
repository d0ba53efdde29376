"""Preparation, the step before an episode: the models it starts from.

:func:`prepare` resolves the setting's pretraining for a scenario (with
``pretraining.detection_gaps = "auto"`` it chooses the probability on an orchard validation
recording, :func:`~dronefl.experiments.gap_choice.resolve_gaps`) and fetches the pretrained
weights from the cache, pretraining them when they are missing
(:func:`~dronefl.experiments.pretrain.pretrained_state`). Everything is cached by content
(the scenario, the setting's model, training and pretraining sub-configs, and the code), so a
second call costs a file read. It runs before any Flower engine of the episode starts; no
configuration object does this work on its own.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from dronefl.config import Scenario
from dronefl.experiments.gap_choice import resolve_gaps
from dronefl.experiments.pretrain import PretrainSpec, pretrained_state
from dronefl.settings import Setting


@dataclass(frozen=True)
class Prepared:
    """What an episode starts from: the resolved pretraining ``spec`` (its detection gaps
    chosen) and the pretrained weights ``state``."""

    spec: PretrainSpec
    state: dict[str, torch.Tensor]


def prepare(
    scenario: Scenario, setting: Setting, kind: str, cache: Path, progress: bool = True
) -> Prepared:
    """The pretrained model of ``kind`` (a :data:`~dronefl.experiments.pretrain.KINDS` name)
    for ``scenario`` as ``setting`` says, from the cache folder ``cache`` (made there when
    missing)."""
    spec = resolve_gaps(PretrainSpec(scenario, setting, kind), cache, progress)
    return Prepared(spec, pretrained_state(spec, cache, progress))
