"""What the companion says: events on Zenoh (and the log), state transitions with their reason."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from companion.supervisor import Announce, Say, Supervisor
from companion.wire.encode import event_body

log = logging.getLogger("companion")

MAX_TEXT = 600  # characters of a message or reason: an operator reads it; a peer must not inflate it


def clip(text: str, n: int = MAX_TEXT) -> str:
    return text if len(text) <= n else text[: n - 15] + f"… ({len(text)} chars)"


class Reporter:
    """Publishes events through `publish(key, body)` (None: log only) and marks the status dirty.
    It is where the supervisor's transitions and policy events are said: it connects itself."""

    def __init__(self, flight: Supervisor, publish: Callable[[str, dict[str, Any]], None] | None = None) -> None:
        self.flight = flight
        self.publish = publish
        self.dirty = True  # the status has news
        flight.connect(announce=self._announce, say=self._say)

    def event(self, kind: str, message: str, **extra: Any) -> None:
        body = event_body(kind, self.flight.state.value, clip(message), **extra)
        log.info("%s: %s %s", kind, body["message"], {k: v for k, v in extra.items() if k != "trajectory"})
        if self.publish is not None:
            try:
                self.publish("events", body)
            except Exception as exc:  # never let a publish error reach the flight logic
                log.warning("event publish failed: %s", exc)
        self.dirty = True

    def _announce(self, a: Announce) -> None:
        self.event("state", a.reason, **{"from": a.src.value, "to": a.dst.value})

    def _say(self, a: Say) -> None:
        self.event(a.kind, a.message, **a.fields)

    def reject(self, key: str, field: str, reason: str, **extra: Any) -> None:
        """A message that was not taken (its content was wrong or cannot be done now)."""
        reason = clip(reason) or "no reason given"
        self.event("rejected", f"{key}: {field + ': ' if field else ''}{reason}", key=key, field=field,
                   reason=reason, **extra)

    def refuse(self, command: str, reason: str, **extra: Any) -> None:
        """A command that is not carried out (not now, or the autopilot said no)."""
        reason = clip(reason) or "no reason given"
        self.event("refused", f"command {command}: {reason}", key="command", command=command, reason=reason, **extra)
