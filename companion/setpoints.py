"""Absolute-deadline scheduling and setpoint sampling.

Deadlines are t_k = t_0 + k / rate from a monotonic clock, never "now +
period": a late wake-up must not push every later setpoint back (drift). When
a wake-up is later than a whole period, the missed ticks are skipped (sending
stale setpoints in a burst helps nobody) and the grid is kept.
"""

from __future__ import annotations

import asyncio
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
