"""The vehicle's response lag behind the setpoints it is streamed, estimated from telemetry.

The lag d is the time shift that best explains the measured positions as the setpoint
stream delayed by d (least squares of p(t) - s(t - d), a constant offset removed, as the
lag is measured on the real autopilots: autopilot-facts.md). The setpoint of time t is the
plan at t + lead, so s(t - d) is the plan at t - d + lead(t - d); each sample keeps the
setpoint stream's positions at every candidate shift, taken when the sample arrives (the
flown plan is trimmed a second behind now).

Settling (issue 26.5): only samples where the plan moves (a lag says nothing at rest) enter
a sliding window; every `UPDATE` s a full grid search over [0, cap] on the window gives a
window estimate (refined between grid points), which moves the estimate by a share
(`SMOOTH`) of the difference. Between moving phases (hover, holds, takeoff) the estimate is
held: nothing at rest changes it. Bounded to [0, cap].
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from planner_core import FloatArray

MIN_SPEED = 0.5  # m/s of the plan: slower samples say little about a time lag
WINDOW = 4.0  # s of moving samples a window estimate fits
MIN_SPAN = 1.5  # s of moving samples before the first window estimate
UPDATE = 0.5  # s between window estimates
SMOOTH = 0.3  # share of a window estimate's difference taken each update
STEP = 0.005  # s between candidate shifts
MAX_JUMP = 0.06  # s: the most one update moves the estimate (one odd window must not swing it)


@dataclass
class LagEstimator:
    cap: float  # s: the largest lag considered
    estimate: float | None = None  # s; None until the first window of motion
    window_estimates: collections.deque[float] = field(default_factory=lambda: collections.deque(maxlen=64))
    _t: collections.deque[float] = field(default_factory=collections.deque)
    _p: collections.deque[FloatArray] = field(default_factory=collections.deque)
    _s: collections.deque[FloatArray] = field(default_factory=collections.deque)  # (n_shifts, 3) each
    _last_update: float = -math.inf

    def __post_init__(self) -> None:
        self.shifts = np.arange(0.0, self.cap + 1e-9, STEP)

    def reset(self) -> None:
        """Forget everything (another vehicle, or the autopilot rebooted)."""
        self.estimate = None
        self.window_estimates.clear()
        self.hold()

    def hold(self) -> None:
        """A new phase of motion starts: the window restarts; the estimate is kept."""
        self._t.clear()
        self._p.clear()
        self._s.clear()

    def add(self, t: float, measured: FloatArray, speed: float, stream_at: Callable[[FloatArray], FloatArray]) -> None:
        """One position sample at monotonic time t. `speed`: the plan's speed then;
        `stream_at(times)`: the setpoint stream's positions at monotonic times (k,) -> (k, 3)."""
        if speed < MIN_SPEED or not np.all(np.isfinite(measured)):
            return
        self._t.append(t)
        self._p.append(np.asarray(measured, dtype=float))
        self._s.append(stream_at(t - self.shifts))
        while self._t and self._t[0] < t - WINDOW:
            self._t.popleft()
            self._p.popleft()
            self._s.popleft()
        if t - self._last_update >= UPDATE and self._t[-1] - self._t[0] >= MIN_SPAN:
            self._last_update = t
            self._update()

    def _update(self) -> None:
        p = np.asarray(self._p)  # (n, 3)
        s = np.asarray(self._s)  # (n, k, 3)
        r = p[:, None, :] - s  # residual at each shift
        r = r - r.mean(axis=0, keepdims=True)  # a constant offset is not a lag
        cost = np.einsum("nkc,nkc->k", r, r)
        i = int(np.argmin(cost))
        d = float(self.shifts[i])
        if 0 < i < len(cost) - 1:  # the parabola through the three lowest points
            c0, c1, c2 = cost[i - 1], cost[i], cost[i + 1]
            den = c0 - 2.0 * c1 + c2
            if den > 0:
                d += 0.5 * STEP * float(c0 - c2) / float(den)
        d = min(max(d, 0.0), self.cap)
        self.window_estimates.append(d)
        if self.estimate is None:
            self.estimate = d
        else:
            move = SMOOTH * (d - self.estimate)
            self.estimate = min(max(self.estimate + max(-MAX_JUMP, min(MAX_JUMP, move)), 0.0), self.cap)


def best_fit_lag(times: FloatArray, measured: FloatArray, stream_at: Callable[[FloatArray], FloatArray],
                 cap: float, step: float = 0.002) -> float:
    """The one shift over a whole record (times (n,), measured (n, 3)) that best explains it as
    the stream delayed: the batch figure the online estimate is compared with."""
    shifts = np.arange(0.0, cap + 1e-9, step)
    costs = []
    for d in shifts:
        r = measured - stream_at(times - d)
        r = r - r.mean(axis=0)
        costs.append(float(np.sum(r * r)))
    return float(shifts[int(np.argmin(costs))])
