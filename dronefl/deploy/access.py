"""Zenoh access control by certificate: who may send which message to whom.

A deployment's processes are known by their *roles*, which their certificates carry as
common names (``world``, ``cloud``, ``launcher``, ``drone-<id>``). An exchange between two
roles is a few Zenoh messages (the ``messages`` of Zenoh's access control), each of one kind
on one key expression, from one role to the other:

* a publication (:func:`publication`): the receiver declares its subscriber to the sender
  (``declare_subscriber``), then the sender puts (``put``);
* a query (:func:`query`): the server declares its queryable to the client
  (``declare_queryable``), the client queries (``query``), the server replies (``reply``);
* liveliness (:func:`liveliness`): the owner declares its token to a watcher
  (``liveliness_token``); the watcher's ``declare_liveliness_subscriber`` and
  ``liveliness_query`` are allowed too, though in peer mode a token reaches every connected
  peer without them (measured with zenoh 1.10).

:func:`access_control` turns the messages one role sends and receives into the
``access_control`` section of its session: with each peer, identified by the common name of
the certificate it presented, exactly those messages (``ingress`` what the peer sends,
``egress`` what this process sends); everything else is denied both ways, and a peer whose
certificate names no role it exchanges with may send nothing at all. Both ends of each hop
check, so a peer that drops its own rules is still held by those of the other end.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass


@dataclass(frozen=True)
class Message:
    """A Zenoh message of kind ``kind`` on the key expression ``key`` that the process of
    role ``sender`` may send to that of role ``receiver``."""

    sender: str
    receiver: str
    kind: str
    key: str


def publication(sender: str, receiver: str, key: str) -> list[Message]:
    """``sender`` puts on ``key`` to ``receiver``, which subscribes to it."""
    return [
        Message(receiver, sender, "declare_subscriber", key),
        Message(sender, receiver, "put", key),
    ]


def query(server: str, client: str, key: str) -> list[Message]:
    """``client`` queries ``key``, which ``server`` answers."""
    return [
        Message(server, client, "declare_queryable", key),
        Message(client, server, "query", key),
        Message(server, client, "reply", key),
    ]


def liveliness(owner: str, watcher: str, token: str, watched: str) -> list[Message]:
    """``watcher``, watching the key expression ``watched``, sees ``owner``'s token
    ``token``."""
    return [
        Message(owner, watcher, "liveliness_token", token),
        Message(watcher, owner, "declare_liveliness_subscriber", watched),
        Message(watcher, owner, "liveliness_query", watched),
    ]


def access_control(role: str, messages: Iterable[Message]) -> dict[str, object]:
    """The ``access_control`` section of the Zenoh configuration of the process of ``role``,
    allowing it ``messages`` (those it neither sends nor receives are left out): one subject
    per peer role (matched by the common name of the peer's certificate), one rule per peer,
    direction and message kind, everything else denied. ``ValueError`` if none of
    ``messages`` is sent or received by ``role``."""
    keys: dict[tuple[str, str, str], set[str]] = {}  # (peer, flow, kind) -> key expressions
    for m in messages:
        if m.sender == role:
            keys.setdefault((m.receiver, "egress", m.kind), set()).add(m.key)
        elif m.receiver == role:
            keys.setdefault((m.sender, "ingress", m.kind), set()).add(m.key)
    if not keys:
        raise ValueError(f"Zenoh access control: {role!r} exchanges no message")
    rules: list[dict[str, object]] = []
    by_peer: dict[str, list[str]] = {}  # peer -> ids of its rules
    for (peer, flow, kind), expressions in sorted(keys.items()):
        rule_id = f"{peer} {flow} {kind}"
        by_peer.setdefault(peer, []).append(rule_id)
        rules.append(
            {
                "id": rule_id,
                "permission": "allow",
                "flows": [flow],
                "messages": [kind],
                "key_exprs": sorted(expressions),
            }
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [{"id": peer, "cert_common_names": [peer]} for peer in by_peer],
        "policies": [
            {"id": peer, "subjects": [peer], "rules": ids} for peer, ids in by_peer.items()
        ],
    }
