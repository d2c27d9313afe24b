"""The vehicle's response lag behind the setpoints it is streamed, estimated from telemetry.

The lag d is the time shift that best explains the measured positions as the setpoint
stream delayed by d (least squares of p(t) - s(t - d), as the lag is measured on the real
autopilots: autopilot-facts.md). The setpoint of time t is the plan at t + lead(t), so
s(t - d) is the plan at t - d + lead(t - d); each sample's residuals at every candidate
shift are taken when it arrives (the flown plan is trimmed a second behind now).

Settling (issue 26.5): the fit is the batch least squares over the motion flown so far,
kept online: each sample where the plan moves (a lag says nothing at rest) adds its squared
residual at every candidate shift to a running cost, slowly forgotten (FORGET samples, ~20 s
at 30 Hz) so that a change of vehicle or load is followed; the estimate is the cost's
minimum (refined between grid points) once MIN_SPAN s of motion are in. A sliding window's
fit swings with what the window holds (a corner, a straight, a stop: the response is not a
pure delay); the running cost does not. Between moving phases (hover, holds, takeoff) the
estimate is held: nothing at rest changes it. Bounded to [0, cap]. Residuals are truncated
at OUTLIER, so that a stall or a gust does not drag the estimate for the next 20 s.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from planner_core import FloatArray

MIN_SPEED = 0.5  # m/s of the plan: slower samples say little about a time lag
MIN_SPAN = 2.0  # s of moving samples before the first estimate
FORGET = 600  # samples: the running cost's memory (~20 s of motion at 30 Hz)
STEP = 0.005  # s between candidate shifts
OUTLIER = 0.5  # m: a residual counts at most this much (a truncated least squares)
# s: the lag each autopilot's vehicle was measured to follow pos+vel+acc setpoints with (best
# fit; /work/shared/autopilot-facts.md): ArduCopter SITL 59-82 ms, PX4 1.15 SIH 0.31-0.38 s. The
# lead starts there (`[setpoints] lead_initial = "autopilot"`) until the estimate has seen motion.
MEASURED_LAG = {"ardupilot": 0.06, "px4": 0.33}
UNKNOWN_AUTOPILOT = "ardupilot"  # whose lag is assumed before an autopilot is found (the shorter)


# The aim beyond the plan (`[setpoints] accel_lead = "autopilot"`, companion.setpoints.sample):
# (k s², time constant s) measured per autopilot. ArduCopter 4.6-dev SITL, stock parameters,
# trailed the paper's scenarios by ~0.09 x the plan's acceleration low-passed over ~1 s beyond
# its time lag (docs/autopilot-limits.md). PX4 was not measured: no aim.
MEASURED_AIM = {"ardupilot": (0.09, 1.0), "px4": (0.0, 0.0)}
# The horizontal aim (`[setpoints] aim_horizontal = "autopilot"`): terms (k s², tc s) measured per
# autopilot. PX4 SIH (EKF2's noise set to SIH's) trails the plan by -0.95 F(1 s) + 3.4 F(4 s)
# beyond a lag of 0.08 s (docs/autopilot-limits.md): SIH's drag, made up only by PX4's velocity
# integral. That is SIH's drag, not a vehicle's: on a response without it (the mock's default
# px4_sih) these terms mis-aim (a demo braked at 1.06 m), and real PX4 was not measured: none by
# default; PX4_SIH_AIM_HORIZONTAL for PX4 SIH (and the mock's px4_sih_drag).
MEASURED_AIM_HORIZONTAL: dict[str, tuple[tuple[float, float], ...]] = {"ardupilot": (), "px4": ()}
PX4_SIH_AIM_HORIZONTAL = ((-0.95, 1.0), (3.4, 4.0))


def initial_aim(setting: float | str, tc: float, autopilot: str | None) -> tuple[float, float]:
    """(accel_lead, accel_lead_tc) the setpoints aim with: `[setpoints] accel_lead` (s², with
    `accel_lead_tc`), or "autopilot": MEASURED_AIM of the autopilot found (none before one is)."""
    if setting == "autopilot":
        return MEASURED_AIM.get(autopilot or "", (0.0, 0.0))
    return float(setting), tc


def initial_aim_horizontal(setting: tuple[tuple[float, float], ...] | str, autopilot: str | None
                           ) -> tuple[tuple[float, float], ...]:
    """The horizontal aim's terms: `[setpoints] aim_horizontal`, or "autopilot": MEASURED_AIM_HORIZONTAL
    of the autopilot found (none before one is)."""
    if setting == "autopilot":
        return MEASURED_AIM_HORIZONTAL.get(autopilot or "", ())
    assert not isinstance(setting, str)
    return setting


def initial_lead(setting: float | str, autopilot: str | None, cap: float) -> float:
    """The lead before an estimate: `[setpoints] lead_initial` (seconds, or "autopilot": the
    lag measured on that autopilot), at most `cap` ([setpoints] lead_max)."""
    if setting == "autopilot":
        lag = MEASURED_LAG.get(autopilot or "", MEASURED_LAG[UNKNOWN_AUTOPILOT])
    else:
        lag = float(setting)
    return min(lag, cap)


@dataclass
class LagEstimator:
    cap: float  # s: the largest lag considered
    estimate: float | None = None  # s; None until MIN_SPAN s of motion
    moving_time: float = 0.0  # s of moving samples taken
    _cost: FloatArray | None = None
    _last: float = -math.inf  # the previous moving sample's time
    history: list[tuple[float, float]] = field(default_factory=list)  # (t, estimate) at each update

    def __post_init__(self) -> None:
        self.shifts = np.arange(0.0, self.cap + 1e-9, STEP)

    def reset(self) -> None:
        """Forget everything (another vehicle, or the autopilot rebooted)."""
        self.estimate = None
        self.moving_time = 0.0
        self._cost = None
        self._last = -math.inf
        self.history.clear()

    def hold(self) -> None:
        """Not flying a plan of ours: nothing to learn; the estimate is kept."""
        self._last = -math.inf

    def add(self, t: float, measured: FloatArray, speed: float, stream_at: Callable[[FloatArray], FloatArray]) -> None:
        """One position sample at monotonic time t. `speed`: the plan's speed then;
        `stream_at(times)`: the setpoint stream's positions at monotonic times (k,) -> (k, 3)."""
        if speed < MIN_SPEED or not np.all(np.isfinite(measured)):
            self._last = -math.inf
            return
        r = np.asarray(measured, dtype=float)[None, :] - stream_at(t - self.shifts)
        # truncated: a moment the vehicle strays for another reason (a stall of the companion, a
        # gust) adds a flat cost, not a pull towards a wrong lag
        r2 = np.minimum(np.einsum("kc,kc->k", r, r), OUTLIER * OUTLIER)
        if not np.all(np.isfinite(r2)):
            return
        self._cost = r2 if self._cost is None else self._cost * (1.0 - 1.0 / FORGET) + r2
        if self._last > -math.inf:
            self.moving_time += min(t - self._last, 0.2)
        self._last = t
        if self.moving_time >= MIN_SPAN:
            self.estimate = self._minimum(self._cost)
            self.history.append((t, self.estimate))
            del self.history[:-2000]

    def _minimum(self, cost: FloatArray) -> float:
        i = int(np.argmin(cost))
        d = float(self.shifts[i])
        if 0 < i < len(cost) - 1:  # the parabola through the three lowest points
            c0, c1, c2 = cost[i - 1], cost[i], cost[i + 1]
            den = c0 - 2.0 * c1 + c2
            if den > 0:
                d += 0.5 * STEP * float(c0 - c2) / float(den)
        return min(max(d, 0.0), self.cap)


def best_fit_lag(times: FloatArray, measured: FloatArray, stream_at: Callable[[FloatArray], FloatArray],
                 cap: float, step: float = 0.002) -> float:
    """The one shift over a whole record (times (n,), measured (n, 3)) that best explains it as
    the stream delayed: the batch figure the online estimate is compared with."""
    shifts = np.arange(0.0, cap + 1e-9, step)
    costs = []
    for d in shifts:
        r = measured - stream_at(times - d)
        costs.append(float(np.sum(r * r)))
    return float(shifts[int(np.argmin(costs))])
