"""Absolute-deadline scheduling and setpoint sampling.

Deadlines are t_k = t_0 + k / rate from a monotonic clock, never "now +
period": a late wake-up must not push every later setpoint back (drift). When
a wake-up is later than a whole period, the missed ticks are skipped (sending
stale setpoints in a burst helps nobody) and the grid is kept.
"""

from __future__ import annotations

import asyncio
import gc
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from planner_core.problem import FloatArray, Trajectory

# The default asyncio selector rounds timeouts to 1 ms; sleeping to slightly
# before the deadline and spinning the rest keeps jitter well under 1 ms.
_SPIN = 0.0015


@dataclass
class DeadlineScheduler:
    t0: float
    rate: float
    k: int = 0

    def deadline(self, k: int) -> float:
        return self.t0 + k / self.rate

    def next_deadline(self, now: float) -> float:
        """Advance to the first deadline not yet in the past (by more than a period)."""
        self.k += 1
        behind = math.floor((now - self.deadline(self.k)) * self.rate)
        if behind > 0:
            self.k += behind
        return self.deadline(self.k)


async def sleep_until(deadline: float, clock: Callable[[], float] = time.monotonic, spin: float = _SPIN) -> float:
    delay = deadline - clock() - spin
    if delay > 0:
        await asyncio.sleep(delay)
    while (now := clock()) < deadline:
        await asyncio.sleep(0)
    return now


@dataclass(frozen=True)
class Setpoint:
    position: FloatArray
    velocity: FloatArray
    acceleration: FloatArray
    yaw: float


def hold_trajectory(position: FloatArray, t: float) -> Trajectory:
    """A verified-by-construction hold: all control points at a measured position."""
    ctrl = np.repeat(np.asarray(position, dtype=float).reshape(1, 1, 3), 10, axis=1)
    return Trajectory(times=np.array([t, t + 1.0]), control_points=ctrl, corridors=None, stats={"hold": True})


class YawPolicy:
    def __init__(self, mode: str, fixed: float, min_speed: float) -> None:
        self.mode = mode
        self.last = fixed
        self.min_speed = min_speed

    def reset(self, measured_yaw: float) -> None:
        """At take-control: start from the vehicle's heading unless the heading is fixed."""
        if self.mode != "fixed" and math.isfinite(measured_yaw):
            self.last = measured_yaw

    def __call__(self, velocity: FloatArray) -> float:
        if self.mode == "velocity" and math.hypot(velocity[0], velocity[1]) >= self.min_speed:
            self.last = math.atan2(velocity[1], velocity[0])
        return self.last


def sample(traj: Trajectory, t: float, yaw: YawPolicy) -> Setpoint:
    """Position, velocity and acceleration at trajectory time t (clamped to its span)."""
    jet = traj.jet(min(max(t, traj.t0), traj.t_end))
    if t >= traj.t_end:
        # Past the end the trajectory is at rest by construction; say so exactly.
        jet[1:] = 0.0
    return Setpoint(jet[0].copy(), jet[1].copy(), jet[2].copy(), yaw(jet[1]))


class GcPacer:
    """Garbage collection at the setpoint loop's pace.

    CPython's automatic collection starts in whichever thread allocates past a threshold and
    holds the GIL for the whole pass, so a pass over a big heap (a decoded 1000-waypoint
    mission, its route) can land in the middle of a tick. `start()` freezes the start-up heap
    (never scanned again) and turns automatic collection off; the loop then calls `after_send`
    right after each setpoint, when the next deadline is furthest away: a young collection once
    enough objects have piled up, an older one every few of those, a full one every
    `full_every` seconds, each only with `slack` seconds left before the next deadline.
    """

    def __init__(self, young: int = 2000, full_every: float = 5.0, slack: float = 0.008,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        self.young = young
        self.full_every = full_every
        self.slack = slack
        self.clock = clock
        self.enabled = False
        self.last_full = -math.inf
        self.worst = 0.0  # longest collection so far (s)
        self.collections = [0, 0, 0]
        self.last: tuple[int, float] | None = None  # (generation, seconds) of the latest collection

    def start(self, now: float) -> None:
        gc.collect()
        gc.freeze()
        gc.disable()
        self.enabled = True
        self.last_full = now

    def stop(self) -> None:
        if self.enabled:
            self.enabled = False
            gc.enable()

    def due(self, now: float) -> int | None:
        """The generation to collect now, or None."""
        if now - self.last_full >= self.full_every:
            return 2
        young, older, _ = gc.get_count()
        if young < self.young:
            return None
        return 1 if older >= 10 else 0

    def after_send(self, now: float, next_deadline: float) -> None:
        if not self.enabled or next_deadline - now < self.slack:
            return
        gen = self.due(now)
        if gen is None:
            return
        t0 = self.clock()
        gc.collect(gen)
        took = self.clock() - t0
        self.worst = max(self.worst, took)
        self.last = (gen, took)
        self.collections[gen] += 1
        if gen == 2:
            self.last_full = now
