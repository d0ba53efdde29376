"""Injected drone faults, for testing that a round survives them (SPEC §10).

A run config value ``faults`` lists what goes wrong, as comma-separated
``ROUND:DRONE:KIND`` items, e.g. ``"2:1:raise,3:2:nan"``: in global round ``ROUND`` drone
``DRONE`` misbehaves as ``KIND`` says:

=========== ===================================================================================
kind        what the drone's ClientApp does
=========== ===================================================================================
raise       trains, then raises (its software crashed): Flower replies with an error
hang        trains, then answers 1 s after the round timeout (it never answers in time)
nan         sends its weights with every value NaN
absurd      sends every weight as 3e4 (finite, fp16-safe, beyond ``MAX_ABS_WEIGHT`` = 1e4)
shape       sends one weight too few (a mis-shaped update)
eval-raise  raises during the round's evaluation
eval-nan    reports a NaN test MSE
=========== ===================================================================================

The ClientApp calls :func:`inject` at one place per phase, on the reply it is about to send.
An empty ``faults`` (the default) injects nothing. :func:`garble_detections` is the data-level
fault: a drone whose detector returns garbage, so that its (finite, plausible-looking) updates
pass every screen and only a robust aggregation rule can keep them out.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from flwr.app import Array, ArrayRecord, MetricRecord, RecordDict

from dronefl.fl.fault_list import EVALUATE_KINDS, TRAIN_KINDS, parse_faults
from dronefl.fl.records import ARRAYS_KEY, METRICS_KEY, WEIGHTS_KEY, FlSettings
from dronefl.logs import OnboardLog

#: The value every weight takes in an ``absurd`` update.
ABSURD_WEIGHT = 3e4
#: How much longer than the round timeout a ``hang`` drone takes to answer, s.
HANG_MARGIN = 1.0


class InjectedFault(RuntimeError):
    """The failure an injected ``raise`` fault raises inside a ClientApp."""


def inject(
    settings: FlSettings, server_round: int, drone_id: int, content: RecordDict
) -> RecordDict:
    """The reply ``content`` of ``drone_id`` in ``server_round`` after the faults
    ``settings.faults`` names for them (train replies carry weights, evaluation replies only
    metrics)."""
    phase = EVALUATE_KINDS if ARRAYS_KEY not in content else TRAIN_KINDS
    for fault in parse_faults(settings.faults):
        if (fault.server_round, fault.drone_id) != (server_round, drone_id):
            continue
        if fault.kind not in phase:
            continue
        if fault.kind in ("raise", "eval-raise"):
            raise InjectedFault(f"drone {drone_id}: injected fault in round {server_round}")
        if fault.kind == "hang":
            time.sleep(settings.round_timeout + HANG_MARGIN)
        elif fault.kind == "eval-nan":
            metrics = MetricRecord(dict(content[METRICS_KEY]))
            metrics["value"] = math.nan
            content = RecordDict({METRICS_KEY: metrics})
        else:
            content = RecordDict(
                {ARRAYS_KEY: _bad_weights(content, fault.kind), METRICS_KEY: content[METRICS_KEY]}
            )
    return content


def _bad_weights(content: RecordDict, kind: str) -> ArrayRecord:
    weights = content[ARRAYS_KEY][WEIGHTS_KEY].numpy()
    if kind == "nan":
        bad = np.full_like(weights, np.nan)
    elif kind == "absurd":
        bad = np.full_like(weights, ABSURD_WEIGHT)
    else:  # shape
        bad = weights[:-1].copy()
    return ArrayRecord({WEIGHTS_KEY: Array(bad)})


def garble_detections(log_path: str | Path, seed: int) -> Path:
    """Rewrite the onboard log at ``log_path`` as if the drone's detector returned garbage: every
    target "detected" at every step, at a box drawn uniformly in the image (centre and size in
    [0, 1]), with confidence 0.9. Odometry and times stay true."""
    log = OnboardLog.load(log_path)
    rng = np.random.default_rng(seed)
    garbage = replace(
        log,
        boxes=rng.uniform(0.0, 1.0, size=log.boxes.shape).astype(np.float32),
        detected=np.ones_like(log.detected),
        confidence=np.full_like(log.confidence, 0.9),
    )
    return garbage.save(log_path)
