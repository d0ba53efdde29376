"""The Flower Grid as the cloud uses it in a deployment.

:class:`DroneGrid` shows a round only the SuperNodes of the drones taking part (``nodes``:
node id -> drone id), so that Flower's strategies sample exactly those, and replaces
``send_and_receive``: it pulls replies every ``poll`` s (Flower's own loop sleeps 3 s between
pulls), gives up after ``timeout`` s, and stops waiting for a drone as soon as ``alive``
says it is gone (its reply will never come).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable

from flwr.app import Message
from flwr.serverapp import Grid


class DroneGrid:
    """``grid`` restricted to ``nodes`` (node id -> drone id), with fast, bounded polling."""

    def __init__(
        self,
        grid: Grid,
        nodes: dict[int, int],
        alive: Callable[[int], bool],
        timeout: float,
        poll: float = 0.2,
    ) -> None:
        self._grid = grid
        self.nodes = dict(nodes)
        self.alive = alive
        self.timeout = timeout
        self.poll = poll

    def __getattr__(self, name: str) -> object:
        return getattr(self._grid, name)

    def get_node_ids(self) -> list[int]:
        return list(self.nodes)

    def send_and_receive(
        self, messages: Iterable[Message], *, timeout: float | None = None
    ) -> list[Message]:
        """Push ``messages``, then pull replies until all arrived, ``timeout`` (at most the
        grid's own) has passed, or every drone still owing a reply is dead."""
        outgoing = list(messages)
        ids = list(self._grid.push_messages(outgoing))
        pending = {
            mid: msg.metadata.dst_node_id for mid, msg in zip(ids, outgoing, strict=True) if mid
        }
        limit = self.timeout if timeout is None else min(timeout, self.timeout)
        deadline = time.monotonic() + limit
        replies: list[Message] = []
        while pending:
            for reply in self._grid.pull_messages(list(pending)):
                replies.append(reply)
                pending.pop(reply.metadata.reply_to_message_id, None)
            if not pending or time.monotonic() > deadline:
                break
            # A node of no known drone may still answer; a known drone's only if it lives.
            if not any(n not in self.nodes or self.alive(self.nodes[n]) for n in pending.values()):
                break
            time.sleep(self.poll)
        return replies
