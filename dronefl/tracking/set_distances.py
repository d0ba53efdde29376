"""Multi-target tracking metrics of an episode from Stone Soup's metric generators.

OSPA (Schuhmacher, Vo & Vo 2008) and GOSPA (Rahmathullah, García-Fernández & Svensson 2017,
alpha = 2) compare the set of fused track positions with the set of true target positions at
every step: a target without a track, or a track without a target, costs the cut-off ``c`` (m);
matched pairs cost their distance (capped at ``c``), combined with exponent ``p``. The per-step
values come from :class:`stonesoup.metricgenerator.ospametric.OSPAMetric` and
:class:`~stonesoup.metricgenerator.ospametric.GOSPAMetric`; here they are averaged over steps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timedelta

import numpy as np

#: Default cut-off distance c (m): a track farther than this from its target counts as missed.
DEFAULT_CUTOFF = 10.0
#: Default exponent p.
DEFAULT_ORDER = 2.0


@dataclass(frozen=True)
class SetDistances:
    """Episode means over steps: ``ospa`` (m) and ``gospa`` (m) distances, with GOSPA's parts
    (m^p; ``gospa = (localisation + missed + false)^(1/p)`` at each step):
    ``gospa_localisation`` the summed ``d^p`` of matched pairs, ``gospa_missed`` and
    ``gospa_false`` the cost ``c^p / 2`` of each target without a track and each track without
    a target; ``cutoff`` c (m) and ``order`` p as used."""

    ospa: float
    gospa: float
    gospa_localisation: float
    gospa_missed: float
    gospa_false: float
    cutoff: float
    order: float


def set_distances(
    truth: np.ndarray,
    tracks: np.ndarray,
    dt: float,
    cutoff: float = DEFAULT_CUTOFF,
    order: float = DEFAULT_ORDER,
) -> SetDistances:
    """OSPA and GOSPA between ``truth`` ``(K, N, 2)`` m (every target exists at every step) and
    ``tracks`` ``(K, N, 2)`` m (NaN where a target has no track), steps ``dt`` s apart."""
    from stonesoup.metricgenerator.ospametric import GOSPAMetric, OSPAMetric
    from stonesoup.types.state import State

    truth = np.asarray(truth, dtype=float)
    tracks = np.asarray(tracks, dtype=float)
    if truth.ndim != 3 or truth.shape[-1] != 2 or tracks.shape != truth.shape:
        raise ValueError(
            f"truth and tracks must both be (K, N, 2), got {truth.shape} and {tracks.shape}"
        )
    if not np.isfinite(truth).all():
        raise ValueError("truth must be finite")
    for name, value in (("cutoff", cutoff), ("order", order), ("dt", dt)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name}: must be a positive number, got {value}")
    if order < 1:
        raise ValueError(f"order: OSPA and GOSPA need p >= 1, got {order}")
    ospa = OSPAMetric(c=cutoff, p=order)
    gospa = GOSPAMetric(c=cutoff, p=order)
    start = datetime(2000, 1, 1)
    values = np.zeros((len(truth), 5))
    for k in range(len(truth)):
        stamp = start + timedelta(seconds=k * dt)
        true_states = [State(p[:, None], timestamp=stamp) for p in truth[k]]
        track_states = [
            State(p[:, None], timestamp=stamp) for p in tracks[k] if np.isfinite(p).all()
        ]
        values[k, 0] = ospa.compute_OSPA_distance(track_states, true_states).value
        g = gospa.compute_gospa_metric(track_states, true_states)[0].value
        values[k, 1:] = (
            g["distance"],
            g["localisation"],
            g["missed"],
            g["false"],
        )
    mean = values.mean(axis=0)
    return SetDistances(*(float(v) for v in mean), float(cutoff), float(order))
