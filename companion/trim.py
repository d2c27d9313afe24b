"""The trim: a slow horizontal correction of the setpoints' position from the measured
tracking error (`[setpoints] trim_tc`, `trim_max`; off by default).

Why: with its default loops PX4 holds its position estimate off the setpoint by its velocity
estimate's bias over `MPC_XY_P` (PX4 SIH: a mean bias of 0.1-0.2 m/s over a mission, an offset
of 0.15-0.39 m, and a slow wander of 0.23-0.38 m on top; docs/autopilot-limits.md). No setpoint
stream that is the plan, however led in time, takes that up; an integral of the error does.

What it may do: each setpoint's position is the aimed point of the verified plan moved by the
trim, and the trim is at most `min(trim_max, tracking allowance)` long. The obstacles are
inflated by the vehicle's radius plus that allowance (docs/autopilot-limits.md), so every
trimmed setpoint lies in the free space the plan's certificate proves, and the tracking brake
still judges the measured position against the plan itself, not against the trimmed setpoint.
Velocity and acceleration stay the plan's. Only while a plan is flown in the air (STREAMING):
on the ground, at a takeoff or a landing the error says nothing about a bias; held meanwhile,
dropped when the companion stops streaming.

Pure: `trim_step(rules, trim, sample)`; the tracking module (companion.tracking) owns the
trim and is its one writer to the setpoint sender.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from planner_core import FloatArray

DT_MAX = 0.2  # s: a longer gap between samples integrates as this much (a stalled link)


@dataclass(frozen=True)
class TrimRules:
    tc: float  # s: the integral's time constant; 0: no trim
    limit: float  # m: the trim's largest length (trim_max, within the tracking allowance)

    @property
    def on(self) -> bool:
        return self.tc > 0.0 and self.limit > 0.0


@dataclass(frozen=True)
class TrimSample:
    at: float  # the sample's monotonic time
    error: FloatArray  # the plan at `at` minus the measured position (local NED)
    integrate: bool  # a plan is flown in the air: the error is evidence of a bias
    streaming: bool  # the companion streams setpoints


@dataclass(frozen=True)
class Trim:
    offset: FloatArray = field(default_factory=lambda: np.zeros(3))  # m, local NED; z is always 0
    at: float | None = None  # the last integrated sample's time


def trim_step(rules: TrimRules, trim: Trim, s: TrimSample) -> Trim:
    """The trim after one position sample."""
    if not rules.on or not s.streaming:
        return Trim() if trim.at is not None or np.any(trim.offset) else trim
    if not s.integrate or not np.all(np.isfinite(s.error)):
        return Trim(trim.offset, None)  # held; the next integration starts afresh
    if trim.at is None:
        return Trim(trim.offset, s.at)
    dt = min(DT_MAX, max(0.0, s.at - trim.at))
    off = trim.offset + np.array([s.error[0], s.error[1], 0.0]) * (dt / rules.tc)
    n = float(np.hypot(off[0], off[1]))
    if n > rules.limit:
        off = off * (rules.limit / n)
    return Trim(off, s.at)
