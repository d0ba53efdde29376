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
from dronefl.fl.checkpoint import CheckpointError
from dronefl.io import atomic_write_bytes
from dronefl.models.online import OnboardRecord
from dronefl.results.episode import ClosedLoopRound, EpisodeLog
from dronefl.sim.world import World
from dronefl.tracking import Fuser
from dronefl.tracking.reports import NoiseReporter

#: The checkpoint's file name in the episode folder.
CHECKPOINT_NAME = "checkpoint.pkl"
#: Written into every checkpoint; a file of another format version is refused.
CHECKPOINT_FORMAT = "dronefl.loop_checkpoint/3"


@dataclass(frozen=True)
class LoopCheckpoint:
    """A closed-loop episode after ``step`` steps (the next step to run is ``step``).

    ``identity`` is the episode's (:meth:`TrackConfig.identity
    <dronefl.experiments.track.TrackConfig.identity>`), to refuse resuming another episode.
    ``fuser`` and ``label_fuser`` are the cloud's filters (``label_fuser`` ``None`` with one
    filter); ``records`` and ``reporters`` each drone's onboard record and noise reporter
    (``None`` where it has none); ``detector``, ``planner`` and ``learner`` those parts'
    ``state()``; ``predictors`` each drone's on-board predictor weights. ``planner_seconds``,
    ``fl_seconds`` and ``wall_seconds`` are the wall time (s) spent so far planning, updating
    models and in all, over every process that ran the episode.
    """

    identity: dict[str, str | int | float]
    step: int
    world: World
    fuser: Fuser
    label_fuser: Fuser | None
    records: list[OnboardRecord]
    reporters: list[NoiseReporter | None]
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
    format: str = CHECKPOINT_FORMAT


def save_loop_checkpoint(path: Path, checkpoint: LoopCheckpoint) -> Path:
    """Write ``checkpoint`` to ``path`` atomically (a kill leaves the previous one whole)."""
    return atomic_write_bytes(path, pickle.dumps(checkpoint, protocol=pickle.HIGHEST_PROTOCOL))


def load_loop_checkpoint(
    path: Path, identity: dict[str, str | int | float]
) -> LoopCheckpoint | None:
    """The checkpoint at ``path`` (``None`` when there is none), which must be of the episode
    ``identity``; raises :class:`CheckpointError` naming the file when it is corrupt, of
    another format version or of another episode (and what differs)."""
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
    check_same_episode(path, checkpoint.identity, identity)
    return checkpoint


def check_same_episode(
    path: Path, saved: dict[str, object], identity: dict[str, str | int | float]
) -> None:
    """Raise :class:`CheckpointError` naming ``path`` and the first part of ``identity`` in
    which the episode saved there (``saved``: its identity, or a ``metrics.json`` config that
    holds it) differs from this one."""
    for name, here in identity.items():
        there = saved.get(name, "<unset>")
        if there != here:
            raise CheckpointError(
                f"{path}: of another episode: {name} is {there!r} there, {here!r} here "
                "(run without --resume to start afresh, or use another --out)"
            )
