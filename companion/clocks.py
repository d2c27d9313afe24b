"""Is our system clock the fleet's? Measured from the others' trajectory messages (issue 24.2).

Times between vehicles are absolute (the system clock): a vehicle whose clock is off by more than
`[fleet] clock_tolerance` publishes trajectories the others place at the wrong times, and reads
theirs wrongly, so the separation they certify does not hold. Every trajectory put carries its
send time on the sender's clock (the Zenoh attachment `{"sent": unix seconds}`); each one heard
gives d = (our clock at arrival) - (its clock at send) = offset + delay, with the delay in
[0, max_delay] (the protocol's assumption). So the offset (ours minus theirs) lies in
[min d - max_delay, min d] over the samples kept: the minimum filters the delays, and one late
put (a busy computer, a retransmission) moves nothing (max d - max_delay would be a tighter
lower bound, but one put over max_delay would then raise an alarm). A vehicle disagrees with us
when that interval lies wholly outside [-tolerance, +tolerance]: certainly off by more (or every
put of the window late by more than max_delay, as broken an assumption). No false alarm while
the clocks agree within the tolerance and the delays stay within max_delay; a clock off by more
than tolerance + max_delay is always found.

Whose clock is off: ours, when we disagree with more than half of the vehicles measured (with
one other vehicle, both sides find themselves off: neither can tell, and both stop planning
against the other). Pure bookkeeping: no clock read here, no I/O.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

WINDOW = 30.0  # s of samples kept per vehicle (a clock that was put right is believed again after this)
MIN_SAMPLES = 5  # samples of a vehicle before it counts (trajectories are published again every second)


@dataclass(frozen=True)
class Offset:
    """Our clock minus theirs, as far as the samples tell: within [lo, hi] (s)."""

    lo: float
    hi: float
    samples: int

    def disagrees(self, tolerance: float) -> bool:
        return self.samples >= MIN_SAMPLES and (self.lo > tolerance or self.hi < -tolerance)

    def text(self) -> str:
        mid = 0.5 * (self.lo + self.hi)
        return f"{mid * 1000:+.0f} ms (within {self.lo * 1000:+.0f}..{self.hi * 1000:+.0f})"


@dataclass
class ClockCheck:
    tolerance: float  # s: [fleet] clock_tolerance
    max_delay: float  # s: [fleet] max_delay
    _seen: dict[str, deque[tuple[float, float]]] = field(default_factory=dict)  # vehicle -> (arrival, d)

    def heard(self, vehicle: str, sent: float, arrived: float) -> None:
        """One trajectory message of `vehicle`, sent at `sent` on its clock and heard at `arrived`
        on ours (both system-clock seconds)."""
        q = self._seen.setdefault(vehicle, deque(maxlen=256))
        q.append((arrived, arrived - sent))
        while q and q[0][0] < arrived - WINDOW:
            q.popleft()

    def forget(self, vehicle: str) -> None:
        self._seen.pop(vehicle, None)

    def offsets(self, now: float) -> dict[str, Offset]:
        out = {}
        for v, q in self._seen.items():
            ds = [d for t, d in q if t >= now - WINDOW]
            if ds:
                out[v] = Offset(min(ds) - self.max_delay, min(ds), len(ds))
        return out

    def ours_off(self, now: float) -> str | None:
        """Why our clock is taken to be off (None: it agrees with the fleet as far as measured)."""
        offs = {v: o for v, o in self.offsets(now).items() if o.samples >= MIN_SAMPLES}
        off = {v: o for v, o in offs.items() if o.disagrees(self.tolerance)}
        if not off or 2 * len(off) <= len(offs):
            return None
        named = ", ".join(f"{v} {o.text()}" for v, o in sorted(off.items()))
        return (f"our system clock disagrees with {len(off)} of the {len(offs)} vehicles heard by more than "
                f"[fleet] clock_tolerance {self.tolerance * 1000:.0f} ms (ours minus theirs: {named}; delays "
                f"assumed within [fleet] max_delay {self.max_delay * 1000:.0f} ms)")

    def others_off(self, now: float) -> list[str]:
        """The vehicles we disagree with (theirs may be the clock that is off)."""
        return sorted(v for v, o in self.offsets(now).items() if o.disagrees(self.tolerance))
