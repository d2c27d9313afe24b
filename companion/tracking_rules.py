"""When the tracking error brakes, and when it warns: one pure function.

`tracking_step(rules, state, reading) -> (state, outputs)` decides, for one position sample
measured against the setpoint of its time, whether the vehicle has been over the limit
(`[safety] tracking_brake`, else `[planner] tracking_allowance`) for TRACKING_SAMPLES samples in
a row (the `tracking` event, and a `Brake` when a plan is being flown), and whether the RMS or
the largest error of the recent samples nears it (the `tracking_margin` warning, once per flight
phase). No I/O, no clock, no asyncio: companion/tracking.py (`Tracking`) builds the reading from
the link's and the supervisor's state, calls this, shows the call to the flight recorder
(/tracking/step) and carries out the outputs (the events, the hold). `python -m companion
replay` runs each recorded call again (companion/replay_tracking.py).
"""

from __future__ import annotations

import zlib
from array import array
from dataclasses import dataclass

import numpy as np

from companion.config import Config

TRACKING_SAMPLES = 3  # position samples in a row above the limit (0.1 s at 30 Hz) before acting
# The tracking measured in flight against [planner] tracking_allowance: an event when the RMS
# over the last TRACKING_WINDOW samples (or the largest error) passes this share of it.
TRACKING_WINDOW = 150  # position samples (~5 s at 30 Hz)
TRACKING_RMS_SHARE = 0.5
TRACKING_MAX_SHARE = 0.8
BRAKE_REASON = "tracking error "  # how every brake of this module's reasons begins (replay finds them by it)


@dataclass(frozen=True)
class TrackingRules:
    """The thresholds (this module's constants) and, from the configuration, whether the brake
    is set apart from the allowance (`[safety] tracking_brake`: the warning names both)."""

    samples: int = TRACKING_SAMPLES
    window: int = TRACKING_WINDOW
    rms_share: float = TRACKING_RMS_SHARE
    max_share: float = TRACKING_MAX_SHARE
    brake_apart: bool = False

    @staticmethod
    def of(cfg: Config) -> TrackingRules:
        return TrackingRules(brake_apart=bool(cfg.safety.tracking_brake))


@dataclass(frozen=True)
class TrackingState:
    """What the rules remember between samples."""

    over: int = 0  # samples in a row above the limit
    said: bool = False  # this excursion's `tracking` event was made (again once back under the limit)
    nearing_said: bool = False  # the margin warning was made (again once the flight phase ends)
    errors: tuple[float, ...] = ()  # the last `window` errors judged, oldest first


@dataclass(frozen=True)
class TrackingSample:
    """One position sample, and what the rules need to know of the moment."""

    error: float | None  # m, to the setpoint of the measurement's time; None: no plan streamed
    flying_ours: bool  # READY, STREAMING, HOLDING or BRAKING, airborne: the only time it is judged
    flying: bool  # STREAMING and airborne: a brake flies a stop (else: holding already)
    limit: float  # m: [safety] tracking_brake, else the tracking allowance; <= 0: no brake
    limit_name: str  # what the limit is called in what is said
    allowance: float  # m: the tracking allowance (what the obstacles are inflated by)
    stop_running: bool  # the stop this module asked for last is still being flown


@dataclass(frozen=True)
class TrackingEvent:
    """Over the limit for `samples` samples in a row: the `tracking` event."""

    error: float
    limit: float
    limit_name: str
    samples: int
    flying: bool

    def message(self) -> str:
        what = "braking to a stop and holding" if self.flying else "holding already"
        return (f"tracking error {self.error:.2f} m over {self.limit_name} {self.limit:.2f} m for {self.samples} "
                f"samples: {what}")


@dataclass(frozen=True)
class MarginEvent:
    """The recent RMS or largest error near the limit: the `tracking_margin` event."""

    rms: float
    worst: float
    limit: float
    limit_name: str
    allowance: float
    samples: int
    brake_apart: bool

    def message(self) -> str:
        if self.brake_apart:  # the brake is set apart from the allowance: name both
            near = "the brake"
            advice = (f"[planner] tracking_allowance {self.allowance:.2f} m is what the obstacles are inflated by, "
                      "the track beyond it is outside what was certified: lower the bounds, or raise the allowance")
        else:
            near, advice = "the allowance", "raise the allowance or lower the bounds"
        return (f"tracking measured near {near}: RMS {self.rms:.2f} m, max {self.worst:.2f} m over the last "
                f"{self.samples} samples, {self.limit_name} {self.limit:.2f} m (warned at {TRACKING_RMS_SHARE:.0%} "
                f"RMS / {TRACKING_MAX_SHARE:.0%} max): {advice}")


@dataclass(frozen=True)
class Brake:
    """Brake to a verified stop and hold, for `reason`."""

    reason: str


Output = TrackingEvent | MarginEvent | Brake
Step = tuple[TrackingState, tuple[Output, ...]]
IDLE = TrackingState()


def tracking_step(rules: TrackingRules, ts: TrackingState, r: TrackingSample) -> Step:
    """The new state and what to do for sample `r`, in order: the margin warning, the
    `tracking` event, the brake. Judged only in the air, flying or holding a plan of ours after
    the takeoff's climb (`flying_ours`): on the ground and while arming an estimate not yet
    settled (PX4 before ready: z wandering by up to 2 m) is no tracking error, and the climb is
    PX4's to shape (it trails by up to 2.5 m). The state is returned itself when nothing
    changes (the recorder records no such call)."""
    err = r.error
    if err is None or not r.flying_ours:
        if ts.over == 0 and not ts.errors and not ts.nearing_said:
            return ts, ()
        return TrackingState(0, ts.said, False, ()), ()
    if r.limit <= 0.0:  # no allowance: no inflation and no brake (planning tests, benches)
        return ts, ()
    out: list[Output] = []
    kept = ts.errors if len(ts.errors) < rules.window else ts.errors[len(ts.errors) - rules.window + 1:]
    errors = (*kept, err)  # the last `window`, as a bounded deque keeps them
    nearing = ts.nearing_said
    if not nearing and len(errors) >= rules.window // 3:
        e = np.asarray(errors)
        rms, worst = float(np.sqrt(np.mean(e * e))), float(e.max())
        if rms >= rules.rms_share * r.limit or worst >= rules.max_share * r.limit:
            nearing = True
            out.append(MarginEvent(rms, worst, r.limit, r.limit_name, r.allowance, len(errors), rules.brake_apart))
    over = ts.over + 1 if err > r.limit else 0
    said = ts.said and over > 0
    if over >= rules.samples and not said and not r.stop_running:
        said = True
        out.append(TrackingEvent(err, r.limit, r.limit_name, over, r.flying))
        if r.flying:
            out.append(Brake(f"{BRAKE_REASON}{err:.2f} m > {r.limit_name} {r.limit:.2f} m"))
    return TrackingState(over, said, nearing, errors), tuple(out)


# -- what a record holds of the state --------------------------------------------------------


@dataclass(frozen=True)
class StateSeen:
    """A TrackingState as recorded: the window of errors by its length and a digest (the
    errors themselves are the readings of the records before), not the 150 numbers."""

    over: int
    said: bool
    nearing_said: bool
    errors: int
    digest: str  # CRC-32 of the errors as float64, hex

    @staticmethod
    def of(ts: TrackingState) -> StateSeen:
        return StateSeen(ts.over, ts.said, ts.nearing_said, len(ts.errors), window_digest(ts.errors))


def window_digest(errors: tuple[float, ...]) -> str:
    return f"{zlib.crc32(array('d', errors).tobytes()):08x}"
