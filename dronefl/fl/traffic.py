"""Communication accounting: the serialized size of every message between cloud and drones.

:class:`CountingGrid` wraps the Grid a strategy talks through and adds up, per global round
and per message type, the bytes of each message sent down (cloud -> drone) and each reply
sent up (drone -> cloud). A message's size is the sum of its serialized objects (the message
and its records, as Flower 1.41 ships them between SuperLink and SuperNode), so the numbers
are the same in simulation and in a deployment.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field

from flwr.app import Message
from flwr.serverapp import Grid
from flwr.supercore.inflatable.inflatable_object import get_all_nested_objects

from dronefl.fl.records import round_of


def message_bytes(message: Message) -> int:
    """Serialized size of ``message`` in bytes (metadata, records and arrays)."""
    return sum(len(obj.deflate()) for obj in get_all_nested_objects(message).values())


@dataclass
class Traffic:
    """Bytes sent down and up, keyed by global round, then by message type."""

    down: dict[int, dict[str, int]] = field(default_factory=lambda: defaultdict(dict))
    up: dict[int, dict[str, int]] = field(default_factory=lambda: defaultdict(dict))

    def add(self, direction: str, server_round: int, kind: str, n_bytes: int) -> None:
        book = self.down if direction == "down" else self.up
        book[server_round][kind] = book[server_round].get(kind, 0) + n_bytes

    def of_round(self, server_round: int) -> dict[str, dict[str, int]]:
        """``{"down": {"train": B, "evaluate": B}, "up": {...}}`` for one round."""
        return {
            "down": dict(self.down.get(server_round, {})),
            "up": dict(self.up.get(server_round, {})),
        }


class CountingGrid:
    """A Grid that counts the bytes of everything sent and received through
    ``send_and_receive`` (which Flower's strategies use) and delegates everything else."""

    def __init__(self, grid: Grid) -> None:
        self._grid = grid
        self.traffic = Traffic()

    def __getattr__(self, name: str) -> object:
        return getattr(self._grid, name)

    def send_and_receive(
        self, messages: Iterable[Message], *, timeout: float | None = None
    ) -> Iterable[Message]:
        outgoing = list(messages)
        server_round = round_of(outgoing[0]) if outgoing else 0
        for message in outgoing:
            kind = message.metadata.message_type
            self.traffic.add("down", server_round, kind, message_bytes(message))
        replies = list(self._grid.send_and_receive(outgoing, timeout=timeout))
        for reply in replies:
            kind = reply.metadata.message_type
            self.traffic.add("up", server_round, kind, message_bytes(reply))
        return replies
