"""Checkpoints of a closed-loop episode: a killed ``dronefl track`` resumes bit-identically
(SPEC §10).

After every FL period (whether or not the method updated its models then) and after the last
step, the episode writes ``<out>/resume.npz`` atomically and fsynced
(:func:`dronefl.io.save_state`; crash point ``write:resume.npz``), so a killed episode
loses at most the period in progress. A :class:`LoopCheckpoint` holds the step to go on from
and every part's state at that step, each as its ``state()`` gives it (numpy arrays and plain
values): the world (vehicles, drones, their random generators, the clock), the cloud's
filters (every track, each pair's adaptive ``R``, the recorded forward pass the pseudo-labels
are smoothed from, the counters), every drone's onboard record and noise reporter, the
episode log, the byte counter, the FL rounds so far, the detector's, the planner's and the
learner's state (weights and round history; the Flower driver is the new session's) and each
drone's on-board predictor weights. A resumed episode builds every part anew from its config
and restores these states into them: the file is data (``.npz`` read with
``allow_pickle=False``), nothing in it can run code or choose what is built.

A resumed episode's numbers equal an uninterrupted one's bit for bit, except the wall-clock
timings (``wall_seconds``, ``fl_seconds``, ``planner_ms_per_step``, each round's ``seconds``):
they add up the time the processes spent on the steps and rounds that were kept, and the time
of one process differs from another's. As between any two runs, a Flower message's size varies
by a few bytes with the random node ids of the engine.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

from dronefl.fl.checkpoint import CheckpointError
from dronefl.io import StateFileError, load_state, save_state

#: The checkpoint's file name in the episode folder.
CHECKPOINT_NAME = "resume.npz"
#: Written into every checkpoint; a file of another format version is refused.
CHECKPOINT_FORMAT = "dronefl.loop_checkpoint/4"


@dataclass(frozen=True)
class LoopCheckpoint:
    """A closed-loop episode after ``step`` steps (the next step to run is ``step``).

    ``identity`` is the episode's (:meth:`TrackConfig.identity
    <dronefl.experiments.track.TrackConfig.identity>`), to refuse resuming another episode.
    Every other field is a part's ``state()``: the ``world``'s, the cloud's ``fuser`` and
    ``label_fuser`` (``None`` with one filter), each drone's ``records`` and ``reporters``
    (``None`` where it has none), the episode ``log`` (its arrays and FL steps), the byte
    ``counter``, the ``rounds`` (``metrics.json``'s entries), the ``detector``'s, the
    ``planner``'s and the ``learner``'s, and ``predictors``: each drone's on-board predictor
    weights. ``planner_seconds``, ``fl_seconds`` and ``wall_seconds`` are the wall time (s)
    spent so far planning, updating models and in all, over every process that ran the
    episode.
    """

    identity: dict
    step: int
    world: dict
    fuser: dict
    label_fuser: dict | None
    records: list
    reporters: list
    log: dict
    counter: dict
    rounds: list
    detector: object
    planner: object
    learner: object
    predictors: dict
    planner_seconds: float
    fl_seconds: float
    wall_seconds: float


def save_loop_checkpoint(path: Path, checkpoint: LoopCheckpoint) -> Path:
    """Write ``checkpoint`` to ``path`` atomically (a kill leaves the previous one whole)."""
    tree = {f.name: getattr(checkpoint, f.name) for f in fields(checkpoint)}
    return save_state(path, {"format": CHECKPOINT_FORMAT, **tree})


def read_loop_checkpoint(path: Path) -> LoopCheckpoint:
    """The checkpoint at ``path``, whatever episode it is of; :class:`CheckpointError` naming
    the file when it is missing, corrupt or of another format version."""
    try:
        tree = load_state(path)
    except StateFileError as exc:
        raise CheckpointError(str(exc)) from None
    if not isinstance(tree, dict) or tree.pop("format", None) != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: not a {CHECKPOINT_FORMAT} episode checkpoint")
    try:
        return LoopCheckpoint(**tree)
    except TypeError:
        raise CheckpointError(f"{path}: not a {CHECKPOINT_FORMAT} episode checkpoint") from None


def load_loop_checkpoint(
    path: Path, identity: dict[str, str | int | float]
) -> LoopCheckpoint | None:
    """The checkpoint at ``path`` (``None`` when there is none), which must be of the episode
    ``identity``; raises :class:`CheckpointError` naming the file when it is corrupt, of
    another format version or of another episode (and what differs)."""
    path = Path(path)
    if not path.is_file():
        return None
    checkpoint = read_loop_checkpoint(path)
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
