"""Checkpoints of a closed-loop episode: a killed ``dronefl track`` resumes bit-identically
(SPEC §10).

After every FL period (whether or not the method updated its models then) and after the last
step, the episode writes ``<out>/checkpoint.pkl`` atomically and fsynced
(:func:`dronefl.io.atomic_write_bytes`; crash point ``write:checkpoint.pkl``), so a killed
episode loses at most the period in progress. A :class:`LoopCheckpoint` holds the step to go on
from and every part's state at that step:

* as they are (plain Python and numpy objects, pickled): the world (vehicles, drones, their
  random generators, the clock), the fuser (every track, each pair's adaptive ``R``, the
  recorded forward pass that the pseudo-labels are smoothed from, its counters), every drone's
  onboard record, the episode log, the byte counter, the FL rounds so far and, with reported
  noise (:mod:`dronefl.tracking.reports`), every drone's running estimate;
* through each part's ``state()`` (the parts that hold runtime objects, which a resumed episode
  builds anew): the detector's (its random generator; an ONNX session or renderer is rebuilt),
  the planner's, the learner's (weights and round history; the Flower driver is the new
  session's) and each drone's on-board predictor weights (its ONNX session is compiled
  from them).

A resumed episode's numbers equal an uninterrupted one's bit for bit, except the wall-clock
timings (``wall_seconds``, ``fl_seconds``, ``planner_ms_per_step``, each round's ``seconds``):
they add up the time the processes spent on the steps and rounds that were kept, and the time
of one process differs from another's. As between any two runs, a Flower message's size varies
by a few bytes with the random node ids of the engine.

A checkpoint is a pickle, which runs code when loaded: it is the episode's own file in its
``--out`` folder and is never to be loaded from elsewhere.
"""

from __future__ import annotations

import pickle
from dataclasses import dataclass
from pathlib import Path

import torch

from dronefl.accounting import ByteCounter
from dronefl.experiments.episode import ClosedLoopRound, EpisodeLog
from dronefl.fl.checkpoint import CheckpointError
from dronefl.io import atomic_write_bytes
from dronefl.models.online import OnboardRecord
from dronefl.sim.world import World
from dronefl.tracking import Fuser
from dronefl.tracking.reports import NoiseReporter

#: The checkpoint's file name in the episode folder.
CHECKPOINT_NAME = "checkpoint.pkl"
#: Written into every checkpoint; a file of another format version is refused.
CHECKPOINT_FORMAT = "dronefl.loop_checkpoint/2"


@dataclass(frozen=True)
class LoopCheckpoint:
    """A closed-loop episode after ``step`` steps (the next step to run is ``step``).

    ``settings`` are the episode's settings (:meth:`TrackConfig.settings
    <dronefl.experiments.track.TrackConfig.settings>`) and ``scenario_hash`` its scenario's
    content hash, to refuse resuming another episode. ``detector``, ``planner`` and ``learner``
    are those parts' ``state()``; ``predictors`` each drone's on-board predictor weights.
    ``planner_seconds``, ``fl_seconds`` and ``wall_seconds`` are the wall time (s) spent so far
    planning, updating models and in all, over every process that ran the episode.
    ``reporters``: each drone's noise estimate (``None`` unless the fusion uses reports).
    ``label_fuser``: the labels' own filter (``None`` unless ``TrackConfig.track_psd`` gives
    the tracks another one; ``fuser`` is then the tracks').
    """

    settings: dict[str, str | int | float | bool]
    scenario_hash: str
    step: int
    world: World
    fuser: Fuser
    records: list[OnboardRecord]
    log: EpisodeLog
    counter: ByteCounter
    rounds: list[ClosedLoopRound]
    detector: object
    planner: object
    learner: object
    predictors: dict[int, dict[str, torch.Tensor]]
    planner_seconds: float
    fl_seconds: float
    wall_seconds: float
    reporters: list[NoiseReporter] | None = None
    format: str = CHECKPOINT_FORMAT
    label_fuser: Fuser | None = None


def save_loop_checkpoint(path: Path, checkpoint: LoopCheckpoint) -> Path:
    """Write ``checkpoint`` to ``path`` atomically (a kill leaves the previous one whole)."""
    return atomic_write_bytes(path, pickle.dumps(checkpoint, protocol=pickle.HIGHEST_PROTOCOL))


def load_loop_checkpoint(
    path: Path, settings: dict[str, str | int | float | bool], scenario_hash: str
) -> LoopCheckpoint | None:
    """The checkpoint at ``path`` (``None`` when there is none), which must be of the episode
    with ``settings`` and ``scenario_hash``; raises :class:`CheckpointError` naming the file
    when it is corrupt, of another format version or of another episode (and which setting
    differs)."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        with path.open("rb") as handle:
            checkpoint = pickle.load(handle)
    except Exception as exc:  # unpickling damaged bytes can raise almost any exception type
        raise CheckpointError(
            f"{path}: truncated or corrupt episode checkpoint ({type(exc).__name__})"
        ) from None
    if not isinstance(checkpoint, LoopCheckpoint) or checkpoint.format != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: not a {CHECKPOINT_FORMAT} episode checkpoint")
    check_same_episode(path, checkpoint.settings, checkpoint.scenario_hash, settings, scenario_hash)
    return checkpoint


def check_same_episode(
    path: Path,
    saved: dict[str, str | int | float | bool],
    saved_hash: str,
    settings: dict[str, str | int | float | bool],
    scenario_hash: str,
) -> None:
    """Raise :class:`CheckpointError` naming ``path`` and the first setting in which the
    episode saved there (``saved`` settings, scenario content hash ``saved_hash``) differs from
    this one's."""
    if saved_hash != scenario_hash:
        raise CheckpointError(
            f"{path}: of another episode: scenario_hash is {saved_hash!r} there, "
            f"{scenario_hash!r} here (another scenario file content)"
        )
    for name in sorted(set(saved) | set(settings)):
        there, here = saved.get(name, "<unset>"), settings.get(name, "<unset>")
        if there != here:
            raise CheckpointError(
                f"{path}: of another episode: {name} is {there!r} there, {here!r} here "
                "(run without --resume to start afresh, or use another --out)"
            )
