"""Communication per drone in KB/s (1 KB = 1000 B) for DroneFL and the centralized baseline.

* DroneFL: the bytes a closed-loop episode counted (:class:`dronefl.wire.ByteCounter`):
  predictions up and controls down every step, model weights down and up every FL round.
* Centralized: every step each drone sends its camera frame, JPEG-encoded as the centralized
  baseline does (:func:`dronefl.perception.uplink.encode_jpeg` at its default quality), with its
  odometry. The frame sizes come from rendered Case 3 frames; one step's uplink is the JPEG
  bytes plus the odometry message of the closed loop (:func:`dronefl.wire.raw_inputs_message`,
  :data:`ODOMETRY_BYTES`), at the scenario's rate (5 Hz).
"""

from __future__ import annotations

import math

import numpy as np

from dronefl.bench.results import CommFigure, EnvironmentUplink, UplinkFigure
from dronefl.bench.vision import Frame
from dronefl.perception.uplink import DEFAULT_JPEG_QUALITY, encode_jpeg
from dronefl.results.episode import EpisodeMetrics
from dronefl.wire import raw_inputs_message

#: Bytes of a centralized drone's odometry message sent with each frame.
ODOMETRY_BYTES = len(raw_inputs_message(0, 0, np.zeros(12)))
#: The paper's Table II, KB/s.
PAPER_KB_PER_S = {"dronefl": 1.56, "centralized": 2.46e3}


def centralized_uplink(frames: dict[str, list[Frame]], rate_hz: float) -> UplinkFigure:
    """KB/s per drone if every frame went to the cloud at ``rate_hz``, per environment of
    ``frames`` and per drone (mean message size over that drone's frames); the headline
    ``kb_per_s`` is the orchard's (where the closed loop is deployed) when it was rendered."""
    per_env = {}
    for env, env_frames in frames.items():
        sizes: dict[int, list[int]] = {}
        for frame in env_frames:
            message = ODOMETRY_BYTES + len(encode_jpeg(frame.image, DEFAULT_JPEG_QUALITY))
            sizes.setdefault(frame.drone_id, []).append(message)
        drones = {d: float(np.mean(s)) * rate_hz / 1000 for d, s in sorted(sizes.items())}
        per_env[env] = EnvironmentUplink(
            kb_per_s=float(np.mean(list(drones.values()))),
            drones=drones,
            frames=len(env_frames),
            mean_jpeg_kb=float(np.mean([m for s in sizes.values() for m in s])) / 1000,
        )
    headline = "orchard" if "orchard" in per_env else next(iter(per_env))
    return UplinkFigure(
        what=(
            f"640x640 frame as JPEG q{DEFAULT_JPEG_QUALITY} + {ODOMETRY_BYTES}-byte odometry"
            f" message, every step at {rate_hz:g} Hz, per drone ({headline})"
        ),
        unit="KB/s",
        kb_per_s=per_env[headline].kb_per_s,
        environment=headline,
        per_environment=per_env,
        paper_kb_per_s=PAPER_KB_PER_S["centralized"],
    )


def dronefl_comm(metrics: EpisodeMetrics, fl_period: float, weights_dtype: str) -> CommFigure:
    """DroneFL's KB/s per drone from a closed-loop episode's ``metrics``
    (:func:`dronefl.experiments.track.run_episode`) with ``weights_dtype`` weights, with the mean
    over drones per message type, and ``at_fl_period``: the same traffic with exactly one round
    per ``fl_period`` s (the episode's last period ends without a round). NaN there when no
    round ran."""
    comm = metrics.communication
    by_kind = {f"{way}:{kind}": comm.mean_per_drone(way, kind) for way, kind in comm.kinds()}
    weights = comm.mean_per_drone(kind="weights")
    rounds = len(metrics.fl_rounds)
    per_round_kb = weights * metrics.sim_seconds / rounds if rounds else math.nan
    total = comm.mean_per_drone()
    steady = total - weights
    bits = np.dtype(weights_dtype).itemsize * 8
    return CommFigure(
        what=f"DroneFL with fp{bits} weights: predictions up + controls down every step, "
        "weights down + up every FL round",
        unit="KB/s",
        kb_per_s=total,
        at_fl_period=steady + per_round_kb / fl_period if rounds else math.nan,
        fl_period_s=fl_period,
        fl_rounds=rounds,
        weights_kb_per_round=per_round_kb,
        by_type=by_kind,
        drones={d: comm.kb_per_s(d) for d in comm.drone_ids},
        paper_kb_per_s=PAPER_KB_PER_S["dronefl"],
        weights_dtype=weights_dtype,
    )
