"""The one owner of what is flown: the mission's route, the active trajectory, its time base
and whether it streams; and what is left of a mission no longer flown.

Every change of what the setpoint thread flies goes through `Control`, one method per change,
each changing the route together with the trajectory: `take` (a hold at a measured position on
a fresh time base; no route), `swap` (checked: the new plan equals the flown one up to the
split; with the mission's route, or a stop that interrupts it), `hold_here` (interrupts it),
`pause` (stops streaming, keeps both) and `release` (neither; what is left of the mission
waits for `start`). So the route is never flown on a trajectory it was not swapped in with,
and a release never leaves one without the other. What a stop left of the mission waits for
`resume` (`interrupted`); a loaded mission (or what a release left) waits for `start`
(`pending`). The thread reads one immutable `Feed` snapshot replaced in one assignment, so it
never samples one trajectory on another's time base. Trajectory time is
`time.monotonic() - t_base`, fixed while we keep control.

Also here, because they are measured against what is flown: the setpoint stream's period
statistics and the message-to-first-setpoint latency of a new plan.
"""

from __future__ import annotations

import collections
import logging
import math
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from companion.mission import remaining
from companion.route import Route
from companion.setpoints import Feed, Setpoint, Tick, YawPolicy, sample
from companion.wire.messages import MissionSpec
from planner_core import Bounds, FloatArray, Trajectory, hold, sampler, segment_at, trim_before

log = logging.getLogger("companion")

# Why Control.swap refused a plan (Control.refusal): each cause its own text.
SWAP_NOTHING = "nothing is flown to swap into"
SWAP_LATE = "the split time had passed when the plan was ready"
SWAP_DIFFERS = ("internal check failed: the new trajectory differs from the flown one before the split "
                "(the swap is refused; the flown plan continues)")
SWAP_JETS = "internal check failed: the new plan's start does not match the flown plan's state at the split"


def swap_refusal(old: Trajectory, new: Trajectory, now: float, lead: float, rate_hz: float, t_split: float) -> str:
    """Why `new` may not replace the flown `old` from trajectory time `t_split`, decided at
    trajectory time `now` with the setpoints `lead` s ahead at `rate_hz`; "" when it may. The
    swap's one rule, a function of these values alone: the flight recorder keeps each call
    (/control/swap) and replay decides it again (companion.replay_swaps)."""
    if t_split <= now + lead + 0.5 / rate_hz:  # setpoints up to now + lead are sent
        return SWAP_LATE
    # single-time samplers: Trajectory.evaluate/jet cost ~0.5 ms a call, on the pop-up's
    # critical path
    so, sn = sampler(old), sampler(new)
    ts = np.linspace(now, t_split, 8)
    if not np.allclose([so.jet(t)[0] for t in ts], [sn.jet(t)[0] for t in ts], atol=1e-6):
        return SWAP_DIFFERS
    old_jet, new_jet = so.jet(t_split), sn.jet(t_split)
    slack = 1e-6 + 1e-6 * np.abs(new_jet) + np.maximum(_rounding(old, t_split), _rounding(new, t_split))[:, None]
    if np.any(np.abs(old_jet - new_jet) > slack):
        return SWAP_JETS
    return ""


# 9!/(9-k)! 2^k eps: the rounding of a degree-9 segment's k-th derivative per metre of its control
# points, before the 1/duration^k; 64x margin (measured up to 1.06x on real stops)
_ROUNDING = 64.0 * np.array([math.perm(9, k) * 2.0**k for k in range(5)]) * float(np.finfo(float).eps)


def _rounding(traj: Trajectory, t: float) -> FloatArray:
    """How far rounding alone may move each derivative (position .. snap) of `traj` at t: it
    grows as 1/duration^k, so a stop's 30 ms leading segment 30 m from the origin rounds its snap
    by ~1e-5, which a plain 1e-6 tolerance took for a stop that does not start where the flown
    plan is (and the companion then held at the measured position instead of flying the stop)."""
    times = traj.times
    s = segment_at(times, t)
    duration = float(times[s + 1] - times[s])
    scale = 1.0 + float(np.max(np.abs(traj.control_points[s])))
    out: FloatArray = _ROUNDING * scale / duration ** np.arange(5)
    return out


def jet_on(traj: Trajectory, t: float) -> FloatArray:
    """`traj`'s jet at trajectory time t, at rest past its end (where a flown plan holds)."""
    jet = traj.jet(min(t, traj.t_end))
    if t >= traj.t_end:
        jet[1:] = 0.0
    return jet


def swap_span(traj: Trajectory, now: float, t_split: float) -> Trajectory:
    """The segments of `traj` that `swap_refusal` reads deciding at `now` for a split at
    `t_split` (those from `now` to `t_split`, clamped to its span), the curve alone: the rule
    decides the same on it, and a recorded decision of a long mission stays small."""
    times = traj.times
    lo, hi = (min(max(t, float(times[0])), float(times[-1])) for t in (min(now, t_split), t_split))
    i0, i1 = segment_at(times, lo), segment_at(times, hi)
    return Trajectory(times[i0:i1 + 2], traj.control_points[i0:i1 + 1])


SwapObserver = Callable[[str, float, float, float, float, Trajectory, Trajectory, str], None]


class FeedTarget(Protocol):
    feed: Feed | None  # and, optionally, `lead` (s): setpoints are sampled that far ahead


class Control:
    """What the setpoint thread flies, and the checks on every change of it."""

    def __init__(self, target: FeedTarget, send: Callable[[Setpoint], None], yaw: YawPolicy, rate_hz: float,
                 on_new_plan: Callable[[Trajectory], None] = lambda _t: None,
                 on_latency: Callable[[str, float, bool, float], None] = lambda *_a: None) -> None:
        self.target = target
        self.send = send
        self.yaw = yaw
        self.rate_hz = rate_hz
        self.on_new_plan = on_new_plan  # publish the plan (called after every change of it)
        self.on_latency = on_latency  # (what, seconds, immediate, sent_mono)
        self._streaming = False
        self._t_base: float | None = None
        self._active: Trajectory | None = None
        # the mission flown: its route, and the trajectory it was swapped in with (the active one)
        self._route: Route | None = None
        self._route_with: Trajectory | None = None
        self._interrupted: MissionSpec | None = None  # what a stop left of the mission, for `resume`
        self._pending: MissionSpec | None = None  # loaded (or left by a release), for `start`
        self._latency_mark: tuple[float, Trajectory, str] | None = None
        # the bounds the flown trajectory keeps within: its mission's, from the swap that brought
        # the mission in, kept through its stops (a stop is verified within them) and an abort
        # (the trajectory flies on); None after a fresh hold or a release
        self._flown_bounds: Bounds | None = None
        self.refusal = ""  # why the last swap was refused ("" after one that was not)
        # each swap decided, shown to the flight recorder: (what, now, lead, rate_hz, t_split,
        # the flown trajectory, the new one, the refusal), trajectory times
        self.observe_swap: SwapObserver = lambda *_call: None
        # the stream, as sent
        self.last_sp: Setpoint | None = None
        self.last_sp_time = 0.0
        self.setpoint_latency: float | None = None
        self.setpoint_gap_max = 0.0
        self.periods: collections.deque[float] = collections.deque(maxlen=1000)

    # -- what is flown (read-only outside) -----------------------------------------

    @property
    def streaming(self) -> bool:
        return self._streaming

    @property
    def t_base(self) -> float | None:
        return self._t_base

    @property
    def active(self) -> Trajectory | None:
        return self._active

    @property
    def route(self) -> Route | None:
        """The mission being flown (its plan is the active trajectory), if any."""
        return self._route

    @property
    def interrupted(self) -> MissionSpec | None:
        return self._interrupted

    @property
    def pending(self) -> MissionSpec | None:
        return self._pending

    def agrees(self) -> bool:
        """The invariant: a route is flown only on the trajectory it was swapped in with, and
        released means neither a route nor a trajectory nor a time base."""
        if self._route is not None and (self._active is not self._route_with or self._t_base is None):
            return False
        return self._active is not None or (self._route is None and self._t_base is None and not self._streaming)

    @property
    def flying(self) -> bool:
        """A plan and its time base are set (streaming or about to)."""
        return self._active is not None and self._t_base is not None

    def now(self) -> float:
        """Trajectory time now."""
        assert self._t_base is not None
        return time.monotonic() - self._t_base

    @property
    def flown_bounds(self) -> Bounds | None:
        """The bounds the flown trajectory keeps within (its mission's, also after a stop or an
        abort ended the mission: the stop still flies from the mission's speed); None: not known
        (a hold from rest, a climb, nothing flown)."""
        return self._flown_bounds

    def lead(self) -> float:
        """How far ahead of now the setpoint thread samples the plan (lag compensation)."""
        return float(getattr(self.target, "lead", 0.0))

    def committed(self) -> float:
        """Trajectory time up to which setpoints have been sent: now plus the lead. A change
        of plan splits after it, so no setpoint already sent is ever contradicted."""
        return self.now() + self.lead()

    def clock(self) -> Callable[[], float]:
        """A clock of committed trajectory time (`committed`) for a worker thread (fixed to
        this time base; the lead read at each call)."""
        t_base = self._t_base
        assert t_base is not None
        return lambda: time.monotonic() - t_base + self.lead()

    def jet(self, t: float) -> FloatArray:
        """The flown plan's jet at trajectory time t (at rest past its end)."""
        assert self._active is not None
        return jet_on(self._active, t)

    def reference(self, at: float | None = None) -> FloatArray | None:
        """The setpoint position of monotonic time `at` (default now; None when not streaming).
        A measurement is compared with the setpoint of its own time, not with that of now."""
        if not self._streaming or self._active is None or self._t_base is None:
            return None
        t = (time.monotonic() if at is None else at) - self._t_base
        return np.asarray(sampler(self._active).jet(t)[0], dtype=float)

    def reference_jet(self, at: float) -> tuple[FloatArray, FloatArray, FloatArray] | None:
        """The plan's position, velocity and acceleration at monotonic time `at` (None when
        not streaming)."""
        if not self._streaming or self._active is None or self._t_base is None:
            return None
        jet = sampler(self._active).jet(at - self._t_base)
        return np.asarray(jet[0], dtype=float), np.asarray(jet[1], dtype=float), np.asarray(jet[2], dtype=float)

    def tracking_error(self, position: FloatArray, at: float) -> float | None:
        """Distance from a position measured at monotonic time `at` to the setpoint of then."""
        ref = self.reference(at)
        if ref is None or not np.all(np.isfinite(position)):
            return None
        return float(np.linalg.norm(position - ref))

    def _set(self, active: Trajectory | None, t_base: float | None, streaming: bool) -> None:
        self._active, self._t_base, self._streaming = active, t_base, streaming
        self.target.feed = Feed(active, t_base) if streaming and active is not None and t_base is not None else None

    # -- the changes -------------------------------------------------------------------

    def take(self, position: FloatArray, measured_yaw: float, reason: str) -> None:
        """Start streaming a hold at a measured position, on a fresh time base."""
        self._end_route(self.now() if self.flying else None, interrupted=False)
        self._set(self._active, self._t_base, False)  # no tick may pair the old plan with the new base
        self.yaw.reset(measured_yaw)
        self._flown_bounds = None
        self._set(hold(position, 0.0), time.monotonic(), True)
        self.on_new_plan(self._active)  # type: ignore[arg-type]
        log.info("taking control: %s", reason)

    def swap(self, new: Trajectory, t_split: float, arrived: float | None, what: str,
             route: Route | None = None) -> bool:
        """Replace the flown plan by `new`, which must equal it before t_split (checked). When
        not, `refusal` says why (one of the SWAP_* texts: each cause its own). `route`: the
        mission `new` flies from t_split (the interrupted one is then flown again); None (a stop,
        a climb): the mission flown so far is interrupted at t_split."""
        old = self._active
        if old is None or self._t_base is None:
            self.refusal = SWAP_NOTHING
            return False
        now, lead = self.now(), self.lead()
        self.refusal = swap_refusal(old, new, now, lead, self.rate_hz, t_split)
        try:
            self.observe_swap(what, now, lead, self.rate_hz, t_split, old, new, self.refusal)
        except Exception:  # a recorder's fault must never change what is flown
            log.exception("control: the swap observer failed")
        if self.refusal in (SWAP_DIFFERS, SWAP_JETS):
            log.error("swap refused: %s", self.refusal)
        if self.refusal:
            return False
        self._set(trim_before(new, now - 1.0), self._t_base, self._streaming)
        if route is not None:
            self._route, self._route_with, self._interrupted = route, self._active, None
            self._flown_bounds = route.mission.bounds
        else:
            self._end_route(t_split, interrupted=True)
        if arrived is not None:
            self._latency_mark = (arrived, self._active, what)  # type: ignore[assignment]
        self.send_now()
        self.on_new_plan(self._active)  # type: ignore[arg-type]
        return True

    def hold_here(self, position: FloatArray) -> None:
        """Hold at the measured position (verified by construction: it does not move); the
        mission flown is interrupted now."""
        now = self.now()
        self._end_route(now, interrupted=True)
        self._set(hold(position, now), self._t_base, self._streaming)
        self.send_now()
        self.on_new_plan(self._active)  # type: ignore[arg-type]

    def release(self) -> None:
        """Stop commanding at once and forget the route, the plan and its time base (a pilot, a
        failsafe, the exit): what is left of the mission, flown or interrupted, waits for
        `start`."""
        if self._route is not None:
            self._end_route(self.now(), interrupted=False)
        elif self._interrupted is not None:
            self._pending = self._interrupted
        self._interrupted = None
        self._flown_bounds = None
        self._set(None, None, False)

    def forget(self) -> None:
        """Abort or land: no mission is flown, loaded or interrupted any more (the trajectory
        flies on until it is changed: a stop, a release)."""
        self._route = self._route_with = self._pending = self._interrupted = None

    def load(self, spec: MissionSpec) -> None:
        """A mission loaded: it waits for `start`."""
        self._pending = spec

    def unload(self, spec: MissionSpec) -> None:
        """`spec` is flown now: it no longer waits for `start` (if it was the one waiting)."""
        if self._pending is spec:
            self._pending = None

    def _end_route(self, t: float | None, *, interrupted: bool) -> None:
        """The mission stops being flown at trajectory time t: what is left of it waits for
        `resume` (`interrupted`: a stop) or for `start` (a release, a fresh hold)."""
        route = self._route
        self._route = self._route_with = None
        if route is None:
            return
        left = None if t is None else remaining(route, t)
        if interrupted:
            self._interrupted = left
        elif left is not None:
            self._pending = left

    def pause(self) -> None:
        """Stop streaming, keeping the plan (a hand-over to the autopilot's own takeoff)."""
        self._set(self._active, self._t_base, False)

    # -- the stream --------------------------------------------------------------------

    def send_now(self) -> None:
        """One setpoint from the flown plan at once, off the periodic grid (which is kept as it
        is): a new plan reaches the autopilot without waiting up to a period for the next tick.
        The periodic statistics ignore it."""
        if not self._streaming or self._active is None or self._t_base is None:
            return
        if getattr(self.target, "withheld", False):  # after a stall, until control is released
            return
        now = time.monotonic()
        try:
            self.send(sample(self._active, now - self._t_base + getattr(self.target, "lead", 0.0), self.yaw,
                             getattr(self.target, "accel_lead", 0.0), getattr(self.target, "accel_lead_tc", 0.0),
                             getattr(self.target, "aim_horizontal", ())))
        except OSError as exc:  # the periodic loop reports a dead link; never fail a swap on it
            log.warning("immediate setpoint not sent: %s", exc)
            return
        self._report_latency(now, immediate=True)

    def on_tick(self, tick: Tick) -> float | None:
        """Bookkeeping of one setpoint tick; returns the trajectory time it flew, if it flew
        the current plan."""
        feed = tick.feed
        if feed is None or tick.setpoint is None:
            self.last_sp = None
            return None
        if tick.gap is not None:
            self.periods.append(tick.gap)
            self.setpoint_gap_max = max(self.setpoint_gap_max, tick.gap)
            if tick.gap > 0.04:
                log.warning("setpoint gap %.1f ms (deadline late by %.1f ms)", tick.gap * 1000,
                            (tick.now - tick.deadline) * 1000)
        self.last_sp, self.last_sp_time = tick.setpoint, tick.now
        self._report_latency(tick.now, immediate=False, sampled=feed.trajectory)
        if feed.trajectory is self._active and feed.t_base == self._t_base:
            return tick.now - feed.t_base
        return None

    def _report_latency(self, now: float, immediate: bool, sampled: Trajectory | None = None) -> None:
        mark = self._latency_mark
        if mark is None or mark[1] is not (self._active if sampled is None else sampled):
            return
        self._latency_mark = None
        self.setpoint_latency = now - mark[0]
        self.on_latency(mark[2], self.setpoint_latency, immediate, now)

    def period_stats(self) -> dict[str, Any] | None:
        """p50/p99/max of the last setpoint periods (ms), measured at the send."""
        if len(self.periods) < 2:
            return None
        p = np.asarray(self.periods) * 1000.0
        return {"p50": round(float(np.percentile(p, 50)), 3), "p99": round(float(np.percentile(p, 99)), 3),
                "max": round(float(p.max()), 3), "n": len(p)}
