"""The list of injected drone faults a run config's ``faults`` names
(``ROUND:DRONE:KIND,...``; what each kind does: :mod:`dronefl.fl.faults`)."""

from __future__ import annotations

from dataclasses import dataclass

TRAIN_KINDS = ("raise", "hang", "nan", "absurd", "shape")
EVALUATE_KINDS = ("eval-raise", "eval-nan")
KINDS = TRAIN_KINDS + EVALUATE_KINDS


@dataclass(frozen=True)
class Fault:
    """Drone ``drone_id`` misbehaves as ``kind`` in global round ``server_round``."""

    server_round: int
    drone_id: int
    kind: str


def parse_faults(text: str) -> tuple[Fault, ...]:
    """``"2:1:raise,3:2:nan"`` -> faults; raises ``ValueError`` naming the bad item."""
    faults = []
    for item in filter(None, (part.strip() for part in text.split(","))):
        parts = item.split(":")
        try:
            server_round, drone_id, kind = int(parts[0]), int(parts[1]), parts[2]
        except (IndexError, ValueError):
            raise ValueError(f"faults: {item!r} is not ROUND:DRONE:KIND") from None
        if len(parts) != 3 or kind not in KINDS or server_round < 1:
            raise ValueError(
                f"faults: {item!r} needs a round >= 1 and a kind of {', '.join(KINDS)}"
            )
        faults.append(Fault(server_round, drone_id, kind))
    return tuple(faults)
