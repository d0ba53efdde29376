"""Closed-loop multi-drone tracking with periodic federated learning (paper Sec. V-C, Table I).

Every step (0.2 s): the world moves; each drone records its odometry and detections and predicts
its assigned targets' next positions (L_p = 10, L_f = 1); the predictions go to the cloud (their
bytes counted), where one EKF per target fuses them; the planner picks every drone's
acceleration; the controls go back down. Every ``fl_period`` s of simulated time the models are
updated from the data recorded so far, labelled by the fused tracks (pseudo-labels; ground truth
only as an ablation):

* ``dronefl``: one federated round (FedAvg of the position-invariant AdaIN model) through the
  Flower apps on the simulation engine, which stays up for the whole episode (the episode runs
  as the ServerApp, :func:`dronefl.fl.simulation.run_session`);
* ``fixed``: the pretrained model, never updated (fixed distributed perception);
* ``centralized``: the cloud runs the ``large`` model on every drone's raw inputs and retrains it
  on the pooled data. With ``--detector yolo`` the raw inputs are each drone's camera frame
  (JPEG, :class:`dronefl.perception.uplink.CloudVisionDetector`: the cloud runs the detector
  on the decoded frame) and its odometry, sent every step; with the projection detector they
  are the boxes and odometry (the output says so). Their bytes are counted.

All models start from the same crop-field pretraining (:mod:`dronefl.experiments.pretrain`);
the episode runs in the orchard by default (SPEC §8).
"""

from __future__ import annotations

import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from dronefl.config import Environment, Scenario, load_scenario
from dronefl.fl.records import WEIGHT_DTYPES, FlSettings
from dronefl.fl.server_app import RoundDriver
from dronefl.fl.simulation import run_session
from dronefl.io import atomic_savez, atomic_write_json
from dronefl.logs import PseudoLabels
from dronefl.models.model import build_model, predictor_config
from dronefl.models.online import OnboardRecord
from dronefl.models.predictor import TrajectoryPredictor
from dronefl.models.train import TrainConfig, train_local
from dronefl.models.windows import WindowSet, WindowSpec, build_windows
from dronefl.perception import make_detector
from dronefl.planning import DroneFLPlanner
from dronefl.progress import progress_bar
from dronefl.sim.world import World
from dronefl.tracking import Fuser, FusionConfig, PositionMeasurement
from dronefl.wire import ByteCounter, ControlMessage, PredictionMessage, raw_inputs_message

TRACK_METHODS: tuple[str, ...] = ("centralized", "fixed", "dronefl")


@dataclass(frozen=True)
class TrackConfig:
    """One closed-loop episode.

    ``case`` 1-3; ``method`` one of :data:`TRACK_METHODS`; ``duration`` s simulated;
    ``environment`` where it is deployed; ``detector`` on the drones; ``fl_period`` s between
    model updates; ``labels`` ``tracks`` (fused EKF tracks, the paper) or ``ground_truth``
    (ablation); ``epochs`` local epochs per update; ``stride`` samples between training windows;
    ``runtime`` of the on-drone predictor; ``weights_dtype`` number format of the model
    weights exchanged by DroneFL (``float32`` or ``float16``); ``pretrained`` folder of the
    pretrained models; ``animate`` also writes the GIF.
    """

    case: int
    out: Path
    method: str = "dronefl"
    seed: int = 0
    duration: float = 600.0
    environment: Environment = "orchard"
    detector: str = "projection"
    fl_period: float = 100.0
    labels: str = "tracks"
    epochs: int = 10
    stride: int = 2
    past_steps: int = 10
    runtime: str = "onnx"
    weights_dtype: str = "float32"
    pretrained: Path = Path("runs/pretrained")
    progress: bool = True
    animate: bool = True

    def __post_init__(self) -> None:
        if self.case not in (1, 2, 3):
            raise ValueError(f"--case: must be 1, 2 or 3, got {self.case}")
        if self.method not in TRACK_METHODS:
            raise ValueError(f"--method: {self.method!r} is not one of {', '.join(TRACK_METHODS)}")
        if self.labels not in ("tracks", "ground_truth"):
            raise ValueError(f"--labels: {self.labels!r} is not one of tracks, ground_truth")
        if self.weights_dtype not in WEIGHT_DTYPES:
            raise ValueError(
                f"--weights-dtype: {self.weights_dtype!r} is not one of {', '.join(WEIGHT_DTYPES)}"
            )
        for name in ("duration", "fl_period"):
            if not getattr(self, name) > 0:
                raise ValueError(f"--{name.replace('_', '-')}: must be positive")


@dataclass
class EpisodeLog:
    """Per-step arrays of an episode (index k is time ``k dt``)."""

    t: np.ndarray
    target_position: np.ndarray  # (K+1, N, 2) true, m
    drone_position: np.ndarray  # (K+1, M, 2) true, m
    drone_velocity: np.ndarray  # (K+1, M, 2) true, m/s
    prediction: np.ndarray  # (K, M, N, 2) drone i's prediction at k of target j at k+1, m
    track_position: np.ndarray  # (K+1, N, 2) fused estimate of time k, m (NaN: no track)
    trace: np.ndarray  # (K, N) Tr P after the update at k
    cost: np.ndarray  # (K,) planner cost J
    fl_steps: list[int] = field(default_factory=list)


def fusion_config(scenario: Scenario) -> FusionConfig:
    """EKF settings for the scenario: the random-walk targets of Case 2 change velocity by about
    1 m/s every second and need a larger process noise than the constant-speed ones."""
    random_walk = any(t.motion == "random_walk" for t in scenario.targets)
    return FusionConfig(acceleration_psd=1.0 if random_walk else 0.1)


def run_episode(config: TrackConfig) -> dict:
    """Run one closed-loop episode; writes ``metrics.json``, ``episode.npz`` and the plots into
    ``config.out`` and returns the metrics."""
    if config.method != "dronefl":
        return _run_episode(config, None)
    settings = FlSettings(
        run_dir=str(Path(config.out) / "fl" / "round_01"),
        out_dir=str(Path(config.out) / "fl" / "global"),
        method="dronefl",
        past_steps=config.past_steps,
        future_steps=1,
        stride=config.stride,
        epochs=config.epochs,
        seed=config.seed,
        labels="tracks",
        weights_dtype=config.weights_dtype,
        train_fraction=1.0,
    )
    n_drones = len(load_scenario(f"case{config.case}").drones)
    return run_session(settings, n_drones, lambda driver: _run_episode(config, driver))


def _run_episode(config: TrackConfig, driver: RoundDriver | None) -> dict:
    from dronefl.experiments.pretrain import pretrained_state

    # One thread: the tiny per-step models are dominated by thread hand-offs otherwise.
    torch.set_num_threads(1)
    scenario = load_scenario(f"case{config.case}")
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    kind = "centralized" if config.method == "centralized" else "dronefl"
    model_config = predictor_config(
        "large" if kind == "centralized" else "dronefl", config.past_steps, 1
    )
    state = pretrained_state(config.case, kind, config.pretrained, progress=config.progress)
    model = build_model(model_config)
    model.load_state_dict(state)
    predictor = TrajectoryPredictor(model, runtime=config.runtime)
    learner = _learner(config, out, state, driver)

    world = World(scenario, config.environment, config.seed)
    cloud_vision = config.method == "centralized" and config.detector == "yolo"
    if cloud_vision:
        from dronefl.perception.uplink import CloudVisionDetector

        detector = CloudVisionDetector.for_world(world)
    else:
        detector = make_detector(config.detector, world)
    fuser = Fuser(scenario.target_ids, scenario.drone_ids, fusion_config(scenario))
    planner = DroneFLPlanner.from_scenario(scenario)
    counter = ByteCounter()
    n_steps = int(round(config.duration * scenario.rate_hz))
    fl_every = int(round(config.fl_period * scenario.rate_hz))
    meta = {"scenario": scenario.name, "environment": config.environment, "seed": config.seed}
    records = [
        OnboardRecord(d.id, d.altitude, scenario.target_ids, d.targets, n_steps, meta)
        for d in scenario.drones
    ]
    log = _empty_log(scenario, n_steps)
    column = {t: j for j, t in enumerate(scenario.target_ids)}
    planner_seconds, fl_seconds, fl_rounds = 0.0, 0.0, []

    started = time.perf_counter()
    with progress_bar(
        f"track case{config.case} {config.method} seed {config.seed}", n_steps, config.progress
    ) as advance:
        for k in range(n_steps):
            _record_truth(log, k, world)
            measurements = []
            for i, (record, odometry, view) in enumerate(
                zip(records, world.odometry(), world.camera_views(), strict=True)
            ):
                detections = detector.detect(view)
                record.append(odometry, detections)
                if config.method == "centralized":
                    boxes = () if cloud_vision else detections  # in the cloud already
                    raw = raw_inputs_message(record.drone_id, k, odometry.vector, boxes)
                    kind = "odometry" if cloud_vision else "raw_inputs"
                    counter.add(record.drone_id, "up", kind, len(raw))
                    if cloud_vision:
                        counter.add(record.drone_id, "up", "frames", detector.last_frame_bytes)
                window = record.window(config.past_steps)
                if window is None:
                    continue
                predicted = predictor.predict(*window)[:, 0]  # (n_assigned, 2) m
                assigned = record.target_ids[record.assigned]
                seen = np.isfinite(predicted).all(axis=1)
                ids, positions = tuple(int(t) for t in assigned[seen]), predicted[seen]
                if config.method != "centralized":  # the cloud fuses what the radio carried
                    data = PredictionMessage(record.drone_id, k, ids, positions[:, None]).encode()
                    counter.add(record.drone_id, "up", "predictions", len(data))
                    received = PredictionMessage.decode(data)
                    ids, positions = received.target_ids, received.positions[:, 0]
                for target_id, position in zip(ids, positions, strict=True):
                    log.prediction[k, i, column[target_id]] = position
                    measurements.append(PositionMeasurement(record.drone_id, target_id, position))
            tracks = fuser.update(world.t + world.dt, measurements)
            for target_id, track in tracks.items():
                log.track_position[k + 1, column[target_id]] = track.position
                log.trace[k, column[target_id]] = np.trace(track.covariance)
            t0 = time.perf_counter()
            plan = planner.plan(world.drone_states(), fuser.forecast(world.dt))
            planner_seconds += time.perf_counter() - t0
            log.cost[k] = plan.cost.total
            commands = []
            for d in scenario.drone_ids:  # each drone flies what it received
                ax, ay = plan.accelerations[d]
                data = ControlMessage(d, k, (float(ax), float(ay))).encode()
                counter.add(d, "down", "control", len(data))
                commands.append(ControlMessage.decode(data).acceleration)
            world.step(np.array(commands))
            if learner is not None and (k + 1) % fl_every == 0 and k + 1 < n_steps:
                t0 = time.perf_counter()
                labels = _labels(config.labels, log, k + 1)
                new_state, entry = learner.update(records, labels, len(fl_rounds) + 1)
                predictor.load_state(new_state)
                seconds = time.perf_counter() - t0
                fl_seconds += seconds
                for d, n_bytes in entry.pop("bytes_per_drone", {}).items():
                    for direction, value in n_bytes.items():
                        counter.add(int(d), direction, "weights", value)
                fl_rounds.append({"t": world.t, "seconds": seconds, **entry})
                log.fl_steps.append(k + 1)
            advance()
        _record_truth(log, n_steps, world)
    wall = time.perf_counter() - started
    metrics = episode_metrics(log, scenario)
    metrics.update(
        {
            "case": config.case,
            "method": config.method,
            "seed": config.seed,
            "environment": config.environment,
            "detector": config.detector,
            "centralized_inputs": _centralized_inputs(
                config, detector.quality if cloud_vision else None
            ),
            "labels": config.labels,
            "sim_seconds": n_steps * scenario.dt,
            "wall_seconds": wall,
            "realtime_factor": n_steps * scenario.dt / wall,
            "fl_seconds": fl_seconds,
            "planner_ms_per_step": 1000 * planner_seconds / n_steps,
            "gating_rejections": int(fuser.rejections),
            "track_resets": int(fuser.resets),
            "fl_rounds": fl_rounds,
            "communication_kb_per_s": counter.kb_per_second(n_steps * scenario.dt),
            "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(config).items()},
        }
    )
    atomic_write_json(out / "metrics.json", metrics)
    _save_log(out / "episode.npz", log)
    from dronefl.report.tracking import plot_episode

    plot_episode(scenario, world.environment, world.camera, log, out, config.method, config.animate)
    return metrics


def episode_metrics(log: EpisodeLog, scenario: Scenario) -> dict:
    """Table I's metrics of an episode (SPEC §8).

    * ``prediction_error`` (m^2): mean ``||z_hat^i_{j,k+1} - z_{j,k+1}||^2`` over every
      prediction a drone made of an assigned target;
    * ``tracking_distance`` (m^2): mean squared horizontal distance drone to assigned target;
    * ``uncertainty``: mean ``Tr P`` over tracked targets and steps;
    * ``speed_change`` (m/s): mean ``||v_k - v_{k-1}||`` over drones and steps;
    * ``total_cost``: mean planner cost ``J`` per step.
    """
    column = {t: j for j, t in enumerate(scenario.target_ids)}
    pred_err, track_dist, coverage = [], [], []
    for i, drone in enumerate(scenario.drones):
        for target_id in drone.targets:
            j = column[target_id]
            predicted = log.prediction[:, i, j]  # (K, 2)
            truth_next = log.target_position[1:, j]  # (K, 2)
            ok = np.isfinite(predicted).all(axis=1)
            pred_err.append(((predicted[ok] - truth_next[ok]) ** 2).sum(axis=1))
            coverage.append(ok)
            gap = log.drone_position[:-1, i] - log.target_position[:-1, j]
            track_dist.append((gap**2).sum(axis=1))
    errors = np.concatenate(pred_err)
    speed_change = np.linalg.norm(np.diff(log.drone_velocity[:-1], axis=0), axis=-1)
    return {
        "prediction_error": float(errors.mean()) if errors.size else float("nan"),
        "tracking_distance": float(np.concatenate(track_dist).mean()),
        "uncertainty": float(np.nanmean(log.trace)),
        "speed_change": float(speed_change.mean()),
        "total_cost": float(log.cost.mean()),
        "prediction_coverage": float(np.concatenate(coverage).mean()),
        "tracking_error": float(
            np.nanmean(((log.track_position - log.target_position) ** 2).sum(axis=-1))
        ),
    }


def _empty_log(scenario: Scenario, n_steps: int) -> EpisodeLog:
    m, n = len(scenario.drones), len(scenario.targets)
    return EpisodeLog(
        t=np.arange(n_steps + 1) * scenario.dt,
        target_position=np.zeros((n_steps + 1, n, 2)),
        drone_position=np.zeros((n_steps + 1, m, 2)),
        drone_velocity=np.zeros((n_steps + 1, m, 2)),
        prediction=np.full((n_steps, m, n, 2), np.nan),
        track_position=np.full((n_steps + 1, n, 2), np.nan),
        trace=np.full((n_steps, n), np.nan),
        cost=np.zeros(n_steps),
    )


def _record_truth(log: EpisodeLog, k: int, world: World) -> None:
    log.target_position[k] = world.targets.position
    log.drone_position[k] = world.drones.position
    log.drone_velocity[k] = world.drones.velocity


def _centralized_inputs(config: TrackConfig, jpeg_quality: int | None) -> str | None:
    """What the centralized baseline's drones send, in words (None for the other methods)."""
    if config.method != "centralized":
        return None
    if jpeg_quality is not None:
        return f"JPEG camera frames (quality {jpeg_quality}) and odometry of every drone"
    return "boxes and odometry of every drone (no images: the projection detector is in use)"


def _labels(source: str, log: EpisodeLog, steps: int) -> np.ndarray:
    """Training labels ``(steps, N, 2)`` for the first ``steps`` steps."""
    if source == "ground_truth":
        return log.target_position[:steps].copy()
    return log.track_position[:steps].copy()


def _save_log(path: Path, log: EpisodeLog) -> None:
    arrays = {k: v for k, v in asdict(log).items() if isinstance(v, np.ndarray)}
    atomic_savez(path, fl_steps=np.array(log.fl_steps, dtype=np.int64), **arrays)


class FederatedLearner:
    """One Flower round (DroneFL) per update through the episode's round ``driver``, continuing
    from the current global model; each round's data (every drone's log so far and the fused
    tracks) is written to ``<out>/fl/round_<k>/`` for the drones to train on, and the global
    checkpoint to ``<out>/fl/global/``."""

    def __init__(self, out: Path, state: dict[str, torch.Tensor], driver: RoundDriver) -> None:
        self.folder = out / "fl"
        shutil.rmtree(self.folder, ignore_errors=True)
        self.state = state
        self.driver = driver

    def update(
        self, records: list[OnboardRecord], labels: np.ndarray, server_round: int
    ) -> tuple[dict[str, torch.Tensor], dict]:
        data = self.folder / f"round_{server_round:02d}"
        _write_round_data(data, records, labels)
        self.state = self.driver.play(self.state, server_round, run_dir=str(data))
        entry = self.driver.history[-1]
        if entry.server_round != server_round:
            raise RuntimeError(f"federated round {server_round} did not finish")
        traffic = {"down": entry.bytes_down, "up": entry.bytes_up}
        return self.state, {
            "round": server_round,
            "train_loss": {str(k): v for k, v in entry.train_loss.items()},
            "rejected": list(entry.rejected),
            "bytes_per_drone": _bytes_per_drone(traffic, records),
        }


class CentralLearner:
    """The centralized baseline's update: the cloud retrains its large model on pooled data."""

    def __init__(self, config: TrackConfig, model_state: dict[str, torch.Tensor]) -> None:
        self.config = config
        self.model = build_model(predictor_config("large", config.past_steps, 1))
        self.model.load_state_dict(model_state)

    def update(
        self, records: list[OnboardRecord], labels: np.ndarray, server_round: int
    ) -> tuple[dict[str, torch.Tensor], dict]:
        spec = WindowSpec(self.config.past_steps, 1, relative=True, stride=self.config.stride)
        pooled = []
        for record in records:
            log = record.to_log()
            pseudo = PseudoLabels(log.t, record.target_ids, labels[: len(log.t)])
            pooled.append(build_windows(log, pseudo.for_log(log), spec))
        data = WindowSet.concat(pooled)
        seed = self.config.seed * 1_000_003 + server_round
        stats = train_local(self.model, data, TrainConfig(self.config.epochs, 1e-3, 128, seed))
        return self.model.state_dict(), {"round": server_round, "train_loss": stats.loss}


def _learner(config: TrackConfig, out: Path, state: dict, driver: RoundDriver | None):
    if config.method == "dronefl":
        if driver is None:
            raise ValueError("the dronefl method needs a federated round driver")
        return FederatedLearner(out, state, driver)
    if config.method == "centralized":
        return CentralLearner(config, state)
    return None


def _write_round_data(folder: Path, records: list[OnboardRecord], labels: np.ndarray) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for record in records:
        record.to_log().save(folder / f"drone_{record.drone_id}.npz")
    t = records[0].t[: records[0].steps]
    PseudoLabels(t, records[0].target_ids, labels[: len(t)]).save(folder / "tracks.npz")


def _bytes_per_drone(traffic: dict, records: list[OnboardRecord]) -> dict[str, dict[str, int]]:
    """Model-weight bytes of one round per drone, ``{drone: {"down": B, "up": B}}``: every drone
    receives and returns a model of the same size, so the round's ``train`` messages split evenly
    (the diagnostic ``evaluate`` messages are not part of the method and are not counted)."""
    share = {d: traffic.get(d, {}).get("train", 0) // len(records) for d in ("down", "up")}
    return {str(r.drone_id): dict(share) for r in records}
