"""The Zenoh key space of one companion: the one source of its key names.

Every key is `<prefix>/<vehicle>/<topic>` (`[zenoh] prefix`, `[vehicle] id`): the service
subscribes to INBOUND, publishes OUTBOUND, answers QUERYABLE and holds the liveliness token
ALIVE while it runs; the `send` / `watch` clients, the router's access control and the docs
(docs/protocol.md) name the same keys.
"""

from __future__ import annotations

INBOUND = ("mission", "obstacles", "change", "command")
OUTBOUND = ("status", "telemetry", "trajectory", "events")
QUERYABLE = ("plan", "status")
ALIVE = "alive"  # the liveliness token: present while the service runs


def key(prefix: str, vehicle: str, topic: str) -> str:
    return f"{prefix}/{vehicle}/{topic}"
