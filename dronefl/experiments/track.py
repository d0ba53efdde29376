"""Closed-loop multi-drone tracking with periodic federated learning (paper Fig. 3, Table I).

Every step (0.2 s), :meth:`ClosedLoop.step` runs the paper's loop with the loop's two halves
(:mod:`dronefl.roles`): each :class:`~dronefl.roles.DroneNode` **detects** its targets,
records the step on board, **predicts** its assigned targets' next positions (L_p -> L_f = 1)
and **sends** them up (bytes counted); the :class:`~dronefl.roles.CloudNode` **fuses** them
(one EKF per target) and **plans** every drone's acceleration, which is **sent** down; the
world **steps**. Every ``learning.period`` s of simulated time the method's
:class:`~dronefl.learners.Learner` updates the models from everything recorded so far,
labelled by the cloud's pseudo-labels:

* ``dronefl``: one federated round through the Flower apps on the simulation engine, which
  stays up for the whole episode (the episode runs as the ServerApp,
  :func:`dronefl.fl.simulation.run_session`);
* ``fixed``: the pretrained model, never updated (fixed distributed perception);
* ``centralized``: the cloud runs the ``large`` model on every drone's raw inputs and retrains
  it on the pooled data. With ``--detector yolo`` the raw inputs are each drone's camera frame
  (JPEG, :class:`dronefl.perception.uplink.CloudVisionDetector`: the cloud runs the detector
  on the decoded frame) and its odometry, sent every step; with the projection detector they
  are the boxes and odometry (the output says so). Their bytes are counted;
* ``centralized-image`` (``--detector yolo`` only): the paper's own centralized baseline. The
  drones send their JPEG frames and odometry (:class:`dronefl.perception.uplink.FrameUplink`),
  nothing detects, and the cloud's image model predicts every assigned target from each drone's
  last L_p frames and retrains on the pooled frames (:mod:`dronefl.learners.image`).

All models start from the same crop-field pretraining, prepared before the episode's Flower
session starts (:func:`dronefl.experiments.prepare.prepare`); the episode runs in the orchard
by default.

After every FL period and after the last step the episode writes a checkpoint
(:mod:`dronefl.experiments.loop_checkpoint`); with ``resume`` a killed episode continues from
it, bit-identically but for the wall-clock timings.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from dronefl.accounting import ByteCounter
from dronefl.config import ENVIRONMENTS, Environment, Scenario
from dronefl.experiments.loop_checkpoint import (
    CHECKPOINT_NAME,
    LoopCheckpoint,
    check_same_episode,
    load_loop_checkpoint,
    save_loop_checkpoint,
)
from dronefl.experiments.prepare import Prepared, prepare
from dronefl.fl.simulation import run_session
from dronefl.learners import LEARNERS, Learner, LearnerSetup
from dronefl.learners.base import arrays_to_weights, weights_to_arrays
from dronefl.learners.federated import session_settings
from dronefl.models.model import PredictorConfig, build_model, count_parameters
from dronefl.models.predictor import RUNTIMES, TrajectoryPredictor
from dronefl.perception import DETECTORS, make_detector
from dronefl.perception.base import Detector
from dronefl.planning import DroneFLPlanner, PlannerConfig
from dronefl.planning.base import Plan, Planner
from dronefl.progress import progress_bar
from dronefl.results.episode import (
    ClosedLoopRound,
    EpisodeLog,
    EpisodeMetrics,
    tracking_metrics,
)
from dronefl.roles import CloudNode, DroneNode, Fused, Received, Uplink, scenario_fuser
from dronefl.serialize import from_json, to_json
from dronefl.settings import Setting
from dronefl.sim.world import World
from dronefl.tracking import Fuser, FusionConfig, set_distances
from dronefl.validation import check_duration, check_one_of, check_seeds
from dronefl.wire import ControlMessage, raw_inputs_message

TRACK_METHODS: tuple[str, ...] = tuple(LEARNERS)
#: :class:`TrackConfig` fields that say how an episode is run, not what runs.
NOT_IDENTITY: tuple[str, ...] = ("out", "pretrained", "progress", "animate", "resume")


@dataclass(frozen=True)
class TrackConfig:
    """One closed-loop episode: ``scenario`` flown for ``duration`` s of simulated time in
    ``environment`` with the drones' ``detector``, by ``method`` (one of
    :data:`TRACK_METHODS`) as ``setting`` says (default: the recommended setting, as on the
    command line), seeded by ``seed``; the drones run their predictor on ``runtime`` (one of
    :data:`~dronefl.models.predictor.RUNTIMES`). ``out`` is the episode folder,
    ``pretrained`` the cache of pretrained models; ``animate`` also writes the GIF;
    ``resume`` reuses a finished episode in ``out`` and else continues from its checkpoint
    (:mod:`dronefl.experiments.loop_checkpoint`) when there is one.
    """

    scenario: Scenario
    out: Path
    setting: Setting = field(default_factory=Setting.load)
    method: str = "dronefl"
    seed: int = 0
    duration: float = 600.0
    environment: Environment = "orchard"
    detector: str = "projection"
    runtime: str = "onnx"
    pretrained: Path = Path("runs/pretrained")
    progress: bool = True
    animate: bool = True
    resume: bool = False

    def __post_init__(self) -> None:
        check_one_of(self.method, TRACK_METHODS, "--method")
        check_one_of(self.environment, ENVIRONMENTS, "--env")
        check_one_of(self.detector, DETECTORS, "--detector")
        check_one_of(self.runtime, RUNTIMES, "runtime")
        check_seeds([self.seed])
        check_duration(self.duration, self.scenario.dt)
        if self.learner.model_input == "frames" and self.detector != "yolo":
            raise ValueError(
                f"--method {self.method}: its model reads camera frames, which only the vision "
                "path renders: use --detector yolo"
            )

    @property
    def learner(self) -> type[Learner]:
        return LEARNERS[self.method]

    @property
    def n_steps(self) -> int:
        """Steps the episode flies."""
        return int(round(self.duration * self.scenario.rate_hz))

    def identity(self) -> dict[str, str | int | float]:
        """What the episode is: every field but :data:`NOT_IDENTITY`, the scenario by name and
        content hash and the setting by its digest (:meth:`~dronefl.settings.Setting.digest`);
        two episodes with equal identities fly the same steps."""
        return {
            "scenario": self.scenario.name,
            "scenario_hash": self.scenario.content_hash,
            "setting": self.setting.digest(),
            "method": self.method,
            "seed": self.seed,
            "duration": self.duration,
            "environment": self.environment,
            "detector": self.detector,
            "runtime": self.runtime,
        }

    def describe(self) -> dict:
        """``metrics.json``'s ``config``: the :meth:`identity`, the whole setting by section
        (``setting_values``, which ``replay --as-flown`` reads back) and its name, and where
        the episode ran."""
        return {
            **self.identity(),
            "setting_name": self.setting.name,
            "setting_values": self.setting.to_dict(),
            "out": str(self.out),
            "pretrained": str(self.pretrained),
        }


@dataclass(frozen=True)
class LoopParts:
    """The parts of the closed loop a researcher swaps to compare, each a factory:
    ``detector(name, world)`` the drones' detector (``name`` is ``TrackConfig.detector``),
    ``fuser(scenario, fusion_config)`` the cloud's fusion (the settings
    :func:`~dronefl.tracking.fusion.cloud_fusion` makes of the setting), ``planner(scenario,
    planner_config)`` the cloud's planner. The predictor and how it learns are the method's
    (:data:`dronefl.learners.LEARNERS`; FL strategies in :data:`dronefl.fl.methods.METHODS`)."""

    detector: Callable[[str, World], Detector] = make_detector
    fuser: Callable[[Scenario, FusionConfig], Fuser] = scenario_fuser
    planner: Callable[[Scenario, PlannerConfig], Planner] = DroneFLPlanner.from_scenario


def run_episode(config: TrackConfig, parts: LoopParts | None = None) -> EpisodeMetrics:
    """Run one closed-loop episode with ``parts`` (default: the paper's); writes
    ``episode.npz``, the plots and, last, ``metrics.json`` into ``config.out`` and returns the
    metrics.

    With ``config.resume`` a finished episode there (``metrics.json``) is returned as it is, and
    else the episode continues from its checkpoint when there is one; either must be of this
    episode (:class:`~dronefl.fl.checkpoint.CheckpointError` naming the file and what differs
    otherwise, raised before any work). The models are prepared next (pretrained if not
    cached); a federated method then runs the whole episode inside one Flower simulation
    session.
    """
    parts = parts or LoopParts()
    out = Path(config.out)
    saved = None
    if config.resume:
        finished = finished_episode(config)
        if finished is not None:
            return finished
        saved = load_loop_checkpoint(out / CHECKPOINT_NAME, config.identity())
    prepared = prepare(
        config.scenario, config.setting, config.learner.model_kind, config.pretrained,
        config.progress,
    )  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    if saved is None:  # an earlier episode's checkpoint must not be resumed into this one
        (out / CHECKPOINT_NAME).unlink(missing_ok=True)
    field_m = (config.scenario.field.width, config.scenario.field.height)
    setup = LearnerSetup(
        out, prepared.state, config.setting, config.seed, field_m, resumed=saved is not None
    )
    if not config.learner.federated:
        return _fly(config, config.learner(setup), prepared, parts, saved)
    n_drones = len(config.scenario.drones)

    def body(driver) -> EpisodeMetrics:
        learner = config.learner(dataclasses.replace(setup, driver=driver))
        return _fly(config, learner, prepared, parts, saved)

    return run_session(session_settings(setup), n_drones, body)


def finished_episode(config: TrackConfig) -> EpisodeMetrics | None:
    """The metrics of the finished episode in ``config.out`` (``None``: no ``metrics.json``);
    raises :class:`~dronefl.fl.checkpoint.CheckpointError` naming the file when it is of
    another episode, :class:`~dronefl.serialize.ResultError` when it is corrupt."""
    path = Path(config.out) / "metrics.json"
    if not path.is_file():
        return None
    metrics = EpisodeMetrics.load(path)
    check_same_episode(path, metrics.config, config.identity())
    return metrics


class ClosedLoop:
    """One episode's world, drones and cloud, stepped as the paper's Fig. 3.

    Built from a ``saved`` checkpoint (:meth:`checkpoint`), the loop continues where that one
    stopped: the parts are built on the saved world and take up their saved state.
    """

    def __init__(
        self,
        config: TrackConfig,
        learner: Learner,
        prepared: Prepared,
        parts: LoopParts,
        saved: LoopCheckpoint | None = None,
    ) -> None:
        scenario, setting = config.scenario, config.setting
        self.config, self.scenario, self.learner = config, scenario, learner
        self.frames_in = learner.model_input == "frames"  # the learner predicts from frames
        self.model_config: PredictorConfig | None = None
        shared = None
        if not self.frames_in:
            self.model_config = prepared.spec.model
            shared = self._predictor(prepared.state)
        self.world = World(scenario, config.environment, config.seed)
        self.cloud_vision = learner.cloud_predicts and config.detector == "yolo"
        if self.frames_in:
            from dronefl.perception.uplink import FrameUplink

            self.detector = FrameUplink.for_world(self.world, learner.frame_px)
        elif self.cloud_vision:
            from dronefl.perception.uplink import CloudVisionDetector

            self.detector = CloudVisionDetector.for_world(self.world)
        else:
            self.detector = parts.detector(config.detector, self.world)
        self.n_steps = config.n_steps
        meta = {"scenario": scenario.name, "environment": config.environment, "seed": config.seed}
        self.drones = [
            DroneNode(
                d,
                scenario,
                setting.drone,
                setting.model.past_steps,
                self.n_steps,
                meta,
                shared,
                radio=not learner.cloud_predicts,
            )  # fmt: skip
            for d in scenario.drones
        ]
        self.cloud = CloudNode(scenario, setting, parts.fuser, parts.planner)
        self.counter = ByteCounter()
        self.log = EpisodeLog.empty(scenario, self.n_steps)
        self.column = {t: j for j, t in enumerate(scenario.target_ids)}
        self.rounds: list[ClosedLoopRound] = []
        self.fl_seconds = 0.0
        if saved is not None:
            self._restore(saved)

    @property
    def records(self) -> list:
        """Every drone's onboard record, in scenario order."""
        return [drone.record for drone in self.drones]

    def checkpoint(self, step: int, wall_seconds: float) -> LoopCheckpoint:
        """The loop's state before step ``step``, after ``wall_seconds`` s of wall time in
        all (see :mod:`dronefl.experiments.loop_checkpoint`)."""
        label_fuser = self.cloud.label_fuser
        return LoopCheckpoint(
            identity=self.config.identity(),
            step=step,
            world=self.world.state(),
            fuser=self.cloud.fuser.state(),
            label_fuser=None if label_fuser is None else label_fuser.state(),
            records=[drone.record.state() for drone in self.drones],
            reporters=[None if d.reporter is None else d.reporter.state() for d in self.drones],
            log=self.log.state(),
            counter=self.counter.state(),
            rounds=[to_json(entry) for entry in self.rounds],
            detector=self.detector.state(),
            planner=self.cloud.planner.state(),
            learner=self.learner.state(),
            predictors={
                d.drone_id: weights_to_arrays(d.predictor.model.state_dict())
                for d in self.drones
                if d.predictor is not None
            },
            planner_seconds=self.cloud.planner_seconds,
            fl_seconds=self.fl_seconds,
            wall_seconds=wall_seconds,
        )

    def _restore(self, saved: LoopCheckpoint) -> None:
        """Take up the ``saved`` state in the parts built anew."""
        self.world.restore(saved.world)
        self.cloud.fuser.restore(saved.fuser)
        if self.cloud.label_fuser is not None:
            self.cloud.label_fuser.restore(saved.label_fuser)
        self.cloud.planner.restore(saved.planner)
        self.cloud.planner_seconds = float(saved.planner_seconds)
        for drone, record, reporter in zip(
            self.drones, saved.records, saved.reporters, strict=True
        ):
            drone.record.restore(record)
            if drone.reporter is not None:
                drone.reporter.restore(reporter)
            if drone.drone_id in saved.predictors:
                drone.predictor = self._predictor(
                    arrays_to_weights(saved.predictors[drone.drone_id])
                )
        self.log = EpisodeLog.from_state(saved.log)
        self.counter.restore(saved.counter)
        self.rounds = [from_json(ClosedLoopRound, entry) for entry in saved.rounds]
        self.detector.restore(saved.detector)
        self.learner.restore(saved.learner)
        self.fl_seconds = float(saved.fl_seconds)

    def step(self, k: int) -> None:
        """Step ``k``: detect -> predict -> send -> fuse -> plan -> send -> step."""
        self._record_truth(k)
        received = []
        for i, (drone, odometry, view) in enumerate(
            zip(self.drones, self.world.odometry(), self.world.camera_views(), strict=True)
        ):
            detections = self.detector.detect(view)
            drone.sense(odometry, detections)
            if self.frames_in:
                self.learner.receive(i, self.detector.last_frame)
            if self.learner.cloud_predicts:
                self._send_raw_inputs(k, drone.record, odometry.vector, detections)
            predicted = (
                self.learner.predict(i, drone.record) if self.frames_in else drone.forecast()
            )
            uplink = drone.uplink(k, predicted)
            self._log_uplink(k, i, uplink)
            received.append(
                Received(
                    drone.drone_id, uplink.sent_ids, uplink.positions[uplink.sent], uplink.reports
                )
            )
        fused = self.cloud.fuse(self.world.t + self.world.dt, received)
        self._record_tracks(k, fused)
        plan = self.cloud.plan(self.world.drone_states(), fused)
        self.log.cost[k] = plan.cost.total
        self.world.step(self._send_controls(k, plan))

    def period_ended(self, k: int) -> bool:
        """Whether an FL period ends after step ``k`` (none ends after the last step)."""
        every = int(round(self.config.setting.learning.period * self.scenario.rate_hz))
        return (k + 1) % every == 0 and k + 1 < self.n_steps

    def learn(self, k: int) -> None:
        """After step ``k``: one model update if an FL period has just ended."""
        if not self.period_ended(k):
            return
        started = time.perf_counter()
        steps = k + 1
        labels = self.cloud.labels(
            self.log.t[:steps], self.log.sent_predictions(), self.log.target_position[:steps]
        )
        if not np.isfinite(labels).any():  # no drone has a label (see learning.label_drones)
            return
        update = self.learner.update(self.records, labels, len(self.rounds) + 1)
        if update is None:
            return
        # A drone that had no label sat the round out: it keeps the model it flies (the
        # round's model learnt nothing from it and may have forgotten its altitude). The
        # image model predicts in the cloud, inside its learner.
        if not self.frames_in:
            new = self._predictor(update.state)
            for drone, own in zip(self.drones, labels, strict=True):
                if np.isfinite(own).any() or self.learner.cloud_predicts:
                    drone.install(new)
        seconds = time.perf_counter() - started
        self.fl_seconds += seconds
        for way, per_drone in (("down", update.weight_bytes_down), ("up", update.weight_bytes_up)):
            for d, n_bytes in per_drone.items():
                self.counter.add(d, way, "weights", n_bytes)
        self.rounds.append(
            ClosedLoopRound(
                round=len(self.rounds) + 1,
                t=self.world.t,
                seconds=seconds,
                train_loss=update.train_loss,
                rejected=update.rejected,
                weight_bytes_down=update.weight_bytes_down,
                weight_bytes_up=update.weight_bytes_up,
            )
        )
        self.log.fl_steps.append(k + 1)

    def finish(self) -> None:
        """Record the truth after the last step."""
        self._record_truth(self.n_steps)

    def _predictor(self, state: dict[str, torch.Tensor]) -> TrajectoryPredictor:
        """A predictor (its runtime compiled) with the weights ``state``."""
        model = build_model(self.model_config)
        model.load_state_dict(state)
        return TrajectoryPredictor(model, runtime=self.config.runtime)

    def _log_uplink(self, k: int, i: int, uplink: Uplink) -> None:
        """Log every prediction drone ``i`` made at step ``k`` and which it sent, and count
        the bytes its radio carried."""
        for target_id, position, sent in zip(
            uplink.target_ids, uplink.positions, uplink.sent, strict=True
        ):
            self.log.prediction[k, i, self.column[target_id]] = position
            self.log.sent[k, i, self.column[target_id]] = sent
        if uplink.prediction_bytes:
            self.counter.add(uplink.drone_id, "up", "predictions", uplink.prediction_bytes)
        if uplink.report_bytes:
            self.counter.add(uplink.drone_id, "up", "noise_reports", uplink.report_bytes)

    def _send_raw_inputs(self, k: int, record, odometry, detections) -> None:
        """The centralized baselines' uplink: odometry and boxes, or odometry and the JPEG
        frame when the cloud detects or its model reads frames."""
        boxes = () if self.cloud_vision else detections  # in the cloud already
        raw = raw_inputs_message(record.drone_id, k, odometry, boxes)
        kind = "odometry" if self.cloud_vision else "raw_inputs"
        self.counter.add(record.drone_id, "up", kind, len(raw))
        if self.cloud_vision:
            self.counter.add(record.drone_id, "up", "frames", self.detector.last_frame_bytes)

    def _send_controls(self, k: int, plan: Plan) -> np.ndarray:
        """Each drone's control as the drone decodes it, ``(M, 2)`` m/s^2."""
        commands = []
        for d in self.scenario.drone_ids:
            ax, ay = plan.accelerations[d]
            data = ControlMessage(d, k, (float(ax), float(ay))).encode()
            self.counter.add(d, "down", "control", len(data))
            commands.append(ControlMessage.decode(data).acceleration)
        return np.array(commands)

    def _record_truth(self, k: int) -> None:
        self.log.target_position[k] = self.world.targets.position
        self.log.drone_position[k] = self.world.drones.position
        self.log.drone_velocity[k] = self.world.drones.velocity

    def _record_tracks(self, k: int, fused: Fused) -> None:
        """Log the planner's tracks and the ``Tr P`` of the fusion's own filter: the
        uncertainty the planner trades against distance."""
        for target_id, track in fused.tracks.items():
            self.log.track_position[k + 1, self.column[target_id]] = track.position
        for target_id, track in fused.fused.items():
            self.log.trace[k, self.column[target_id]] = np.trace(track.covariance)


def _fly(
    config: TrackConfig,
    learner: Learner,
    prepared: Prepared,
    parts: LoopParts,
    saved: LoopCheckpoint | None,
) -> EpisodeMetrics:
    """Fly the episode (from the ``saved`` checkpoint's step, when given), checkpointing after
    every FL period and at the end, and write its results; the detector is closed at the end,
    whatever happened."""
    # One thread: the tiny per-step models are dominated by thread hand-offs otherwise.
    torch.set_num_threads(1)
    loop = ClosedLoop(config, learner, prepared, parts, saved)
    try:
        return _fly_loop(config, loop, saved)
    finally:
        loop.detector.close()


def _fly_loop(
    config: TrackConfig, loop: ClosedLoop, saved: LoopCheckpoint | None
) -> EpisodeMetrics:
    """The steps of :func:`_fly` from the checkpoint's on, then its checkpoint and results."""
    out = Path(config.out)
    first, wall_before = (saved.step, saved.wall_seconds) if saved else (0, 0.0)
    name = f"track {config.scenario.name} {config.method} seed {config.seed}"
    started = time.perf_counter()

    def wall() -> float:
        return wall_before + time.perf_counter() - started

    with progress_bar(name, loop.n_steps, config.progress) as advance:
        advance(first)
        for k in range(first, loop.n_steps):
            loop.step(k)
            loop.learn(k)
            if loop.period_ended(k):
                save_loop_checkpoint(out / CHECKPOINT_NAME, loop.checkpoint(k + 1, wall()))
            advance()
    loop.finish()
    wall_seconds = wall()
    save_loop_checkpoint(out / CHECKPOINT_NAME, loop.checkpoint(loop.n_steps, wall_seconds))
    metrics = _metrics(config, loop, wall_seconds)
    loop.log.save(out / "episode.npz")
    from dronefl.report.tracking import plot_episode

    world = loop.world
    plot_episode(
        config.scenario, world.environment, world.camera, loop.log, out, config.method,
        config.animate,
    )  # fmt: skip
    metrics.save(out / "metrics.json")  # last: it marks the episode finished
    return metrics


def _metrics(config: TrackConfig, loop: ClosedLoop, wall: float) -> EpisodeMetrics:
    sim_seconds = loop.n_steps * config.scenario.dt
    return EpisodeMetrics(
        scenario=config.scenario.name,
        scenario_hash=config.scenario.content_hash,
        method=config.method,
        seed=config.seed,
        environment=config.environment,
        detector=config.detector,
        labels=config.setting.learning.labels,
        tracking=tracking_metrics(loop.log, config.scenario),
        set_distances=set_distances(
            loop.log.target_position, loop.log.track_position, config.scenario.dt
        ),
        fl_rounds=tuple(loop.rounds),
        communication=loop.counter.rates(sim_seconds),
        sim_seconds=sim_seconds,
        wall_seconds=wall,
        fl_seconds=loop.fl_seconds,
        planner_ms_per_step=1000 * loop.cloud.planner_seconds / loop.n_steps,
        gating_rejections=loop.cloud.rejections,
        track_resets=loop.cloud.resets,
        centralized_inputs=_centralized_inputs(loop),
        config=config.describe(),
        model_input=loop.learner.model_input,
        model_parameters=_parameters(loop),
    )


def _centralized_inputs(loop: ClosedLoop) -> str | None:
    """What the centralized baseline's drones send, in words (None for the other methods)."""
    if not loop.learner.cloud_predicts:
        return None
    if loop.frames_in:
        return (
            f"JPEG camera frames (quality {loop.detector.quality}) and odometry of every drone; "
            f"no detector: the cloud's image model reads the frames at {loop.learner.frame_px} px"
        )
    if loop.cloud_vision:
        return f"JPEG camera frames (quality {loop.detector.quality}) and odometry of every drone"
    return "boxes and odometry of every drone (no images: the projection detector is in use)"


def _parameters(loop: ClosedLoop) -> int:
    """Trainable parameters of the model the method flies (the image model's, in the cloud,
    for a method whose model reads frames)."""
    if loop.frames_in:
        return loop.learner.parameters
    return count_parameters(loop.drones[0].predictor.model)
