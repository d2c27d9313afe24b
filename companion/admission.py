"""Inbound messages admitted at a bounded rate before they reach the event loop.

A peer may put thousands of valid messages in a fraction of a second (issue 21: 5,000 obstacle
updates in 0.11 s stalled the loop for 610 ms: a loop callback and a decode per message). Zenoh's
threads ask here first: a token bucket per kind (`[limits] inbound_rate` messages a second,
`inbound_burst` at once) decides in Zenoh's thread, before anything is scheduled on the loop.
What is refused is counted per kind and said by the loop at most once a second.
"""

from __future__ import annotations

import threading


class Admission:
    def __init__(self, rate: float, burst: int) -> None:
        self.rate = rate
        self.burst = float(burst)
        self._lock = threading.Lock()
        self._buckets: dict[str, tuple[float, float]] = {}  # kind -> (tokens, at)
        self._refused: dict[str, int] = {}
        self.refused = 0  # since start

    def allow(self, kind: str, arrived: float) -> bool:
        """From any thread: True when a message of `kind` arriving at `arrived` may be queued."""
        with self._lock:
            tokens, at = self._buckets.get(kind, (self.burst, arrived))
            tokens = min(self.burst, tokens + max(0.0, arrived - at) * self.rate)
            if tokens < 1.0:
                self._buckets[kind] = (tokens, arrived)
                self._refused[kind] = self._refused.get(kind, 0) + 1
                self.refused += 1
                return False
            self._buckets[kind] = (tokens - 1.0, arrived)
            return True

    def refusals(self) -> dict[str, int]:
        """Messages refused per kind since the last call."""
        with self._lock:
            out, self._refused = self._refused, {}
        return out
