"""Byte accounting of the closed loop: what every drone sends and receives, by message kind.

:class:`ByteCounter` adds up the serialized bytes of every message (the per-step wire formats of
:mod:`dronefl.wire`, JPEG frames, model weights counted by :mod:`dronefl.fl.traffic`) per
(drone, direction, kind); :meth:`ByteCounter.rates` turns them into a :class:`Communication`:
KB/s per drone (1 KB = 1000 B) over the simulated time.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import Literal

import numpy as np

Direction = Literal["up", "down"]
DIRECTIONS: tuple[str, ...] = ("up", "down")


@dataclass(frozen=True)
class TrafficRate:
    """The rate of one kind of message of one drone: ``direction`` ``up`` (drone -> cloud) or
    ``down``; ``kind`` e.g. ``predictions``, ``control``, ``weights``, ``frames``;
    ``kb_per_s`` in KB/s of simulated time."""

    drone_id: int
    direction: str
    kind: str
    kb_per_s: float


@dataclass(frozen=True)
class Communication:
    """Traffic of a run: every (drone, direction, kind) rate, KB/s."""

    rates: tuple[TrafficRate, ...]

    @property
    def drone_ids(self) -> tuple[int, ...]:
        return tuple(sorted({r.drone_id for r in self.rates}))

    def kb_per_s(
        self, drone_id: int | None = None, direction: str | None = None, kind: str | None = None
    ) -> float:
        """Sum of the rates matching every given filter, KB/s."""
        return float(
            sum(
                r.kb_per_s
                for r in self.rates
                if (drone_id is None or r.drone_id == drone_id)
                and (direction is None or r.direction == direction)
                and (kind is None or r.kind == kind)
            )
        )

    def mean_per_drone(self, direction: str | None = None, kind: str | None = None) -> float:
        """Mean over drones of each drone's matching rate, KB/s (0 without traffic)."""
        drones = self.drone_ids
        if not drones:
            return 0.0
        return float(np.mean([self.kb_per_s(d, direction, kind) for d in drones]))

    def kinds(self) -> tuple[tuple[str, str], ...]:
        """Every (direction, kind) that carried bytes."""
        return tuple(sorted({(r.direction, r.kind) for r in self.rates}))


class ByteCounter:
    """Bytes sent per (drone, direction, message kind), e.g. ``(2, "up", "predictions")``."""

    def __init__(self) -> None:
        self._bytes: dict[tuple[int, str, str], int] = defaultdict(int)

    def add(self, drone_id: int, direction: str, kind: str, n_bytes: int) -> None:
        """Count ``n_bytes`` sent ``direction`` (``up`` to the cloud or ``down``)."""
        if direction not in DIRECTIONS:
            raise ValueError(f"direction must be 'up' or 'down', got {direction!r}")
        self._bytes[(drone_id, direction, kind)] += n_bytes

    def total(
        self, drone_id: int | None = None, direction: str | None = None, kind: str | None = None
    ) -> int:
        """Bytes matching every given filter."""
        return sum(
            n
            for (d, way, k), n in self._bytes.items()
            if (drone_id is None or d == drone_id)
            and (direction is None or way == direction)
            and (kind is None or k == kind)
        )

    def state(self) -> dict[tuple[int, str, str], int]:
        """Every count so far, for an episode checkpoint."""
        return dict(self._bytes)

    def restore(self, state: dict[tuple[int, str, str], int]) -> None:
        """Continue counting from ``state`` (:meth:`state`)."""
        self._bytes = defaultdict(int, {tuple(k): int(n) for k, n in state.items()})

    def rates(self, seconds: float) -> Communication:
        """Every counted (drone, direction, kind) as KB/s over ``seconds`` of simulated time."""
        if not seconds > 0:
            raise ValueError(f"seconds must be positive, got {seconds}")
        return Communication(
            tuple(
                TrafficRate(d, way, kind, n / 1000 / seconds)
                for (d, way, kind), n in sorted(self._bytes.items())
            )
        )
