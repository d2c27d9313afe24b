"""Link and vehicle faults: packet drop, latency, link pause, reboot, arming rejection."""

from __future__ import annotations

import heapq
import itertools
import random
import re
from dataclasses import dataclass, field
from typing import Any


@dataclass
class FaultSpec:
    """Faults given on the command line; times in simulated seconds since start."""

    drop: float = 0.0
    latency_s: float = 0.0
    pauses: list[tuple[float, float]] = field(default_factory=list)  # (at, duration)
    reboots: list[float] = field(default_factory=list)
    reject_arming: bool = False


def parse_seconds(text: str, field_name: str) -> float:
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*(ms|s)?\s*", text)
    if not m:
        raise ValueError(f"--fault {field_name}: cannot read duration {text!r} (e.g. 50ms, 0.05s, 3)")
    value = float(m.group(1))
    return value / 1000.0 if m.group(2) == "ms" else value


def parse_faults(items: list[str]) -> FaultSpec:
    """Parse repeated ``--fault`` values: drop=F, latency=50ms, pause=AT:DUR, reboot=AT, reject-arming."""
    spec = FaultSpec()
    for item in items:
        key, _, value = item.partition("=")
        key = key.strip().lower()
        if key == "drop":
            try:
                spec.drop = float(value)
            except ValueError:
                raise ValueError(f"--fault drop: not a number: {value!r}") from None
            if not 0.0 <= spec.drop <= 1.0:
                raise ValueError(f"--fault drop: fraction must be in [0, 1], got {spec.drop}")
        elif key == "latency":
            spec.latency_s = parse_seconds(value, "latency")
        elif key == "pause":
            at, sep, dur = value.partition(":")
            if not sep:
                raise ValueError(f"--fault pause: expected AT:SECONDS, got {value!r}")
            spec.pauses.append((parse_seconds(at, "pause"), parse_seconds(dur, "pause")))
        elif key == "reboot":
            spec.reboots.append(parse_seconds(value, "reboot"))
        elif key in ("reject-arming", "reject_arming"):
            spec.reject_arming = value.strip().lower() not in ("0", "false", "no")
        else:
            raise ValueError(
                f"--fault: unknown fault {key!r}; valid: drop, latency, pause, reboot, reject-arming"
            )
    return spec


class LinkFaults:
    """Applies drop / latency / pause to packets in both directions.

    Packets are delayed through a heap keyed by release time (simulated clock).
    """

    def __init__(self, spec: FaultSpec, seed: int | None) -> None:
        self.drop = spec.drop
        self.latency_s = spec.latency_s
        self.pause_until = -1.0
        self.rng = random.Random(seed)
        self._heap: list[tuple[float, int, Any]] = []
        self._counter = itertools.count()
        self.dropped = {"in": 0, "out": 0}
        self.passed = {"in": 0, "out": 0}

    def paused(self, now: float) -> bool:
        return now < self.pause_until

    def heal(self) -> None:
        """No more drops, latency or pause (packets already delayed still arrive when due)."""
        self.drop, self.latency_s, self.pause_until = 0.0, 0.0, -1.0

    def pause(self, now: float, seconds: float) -> None:
        self.pause_until = max(self.pause_until, now + seconds)

    def admit(self, now: float, direction: str) -> bool:
        """Whether a packet survives the link now (pause and random drop)."""
        if self.paused(now) or (self.drop > 0.0 and self.rng.random() < self.drop):
            self.dropped[direction] += 1
            return False
        self.passed[direction] += 1
        return True

    def push(self, now: float, item: Any) -> None:
        heapq.heappush(self._heap, (now + self.latency_s, next(self._counter), item))

    def due(self, now: float) -> list[Any]:
        out = []
        while self._heap and self._heap[0][0] <= now:
            out.append(heapq.heappop(self._heap)[2])
        return out

    def next_release(self) -> float | None:
        return self._heap[0][0] if self._heap else None

    def clear(self) -> None:
        self._heap.clear()
