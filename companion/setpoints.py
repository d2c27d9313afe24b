"""Absolute-deadline scheduling, setpoint sampling and the setpoint thread.

Deadlines are t_k = t_0 + k / rate from a monotonic clock, never "now +
period": a late wake-up must not push every later setpoint back (drift). When
a wake-up is later than a whole period, the missed ticks are skipped (sending
stale setpoints in a burst helps nobody) and the grid is kept.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import multiprocessing
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from planner_core import FloatArray, Trajectory, sampler

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


# [setpoints] accel_lead_tc > 0: the plan's acceleration low-passed over this many time
# constants of its past, in steps of FILTER_STEP s (a Riemann sum of the exponential kernel: the
# acceleration is smooth, bounded snap, so 40 ms steps are exact to well under a millimetre of aim).
# The kernel's tail beyond the span is lumped at its end: e^-6 = 0.25 % of it, within which the
# target's velocity F' = (a - F) / tc is F's derivative (at 4 spans, 1.8 %: 0.065 m/s of velocity
# with PX4 SIH's horizontal k of 3.4 s²)
FILTER_SPAN = 6.0
FILTER_STEP = 0.04


@functools.lru_cache(maxsize=8)
def filter_weights(tc: float) -> tuple[FloatArray, FloatArray]:
    """(lags s, weights) of the first-order low-pass with time constant tc as a sum over the past:
    F(t) = sum_i w_i a(t - s_i); the last weight carries the kernel's tail (exact for a constant)."""
    n = max(1, math.ceil(FILTER_SPAN * tc / FILTER_STEP))
    edges: FloatArray = np.arange(n + 1, dtype=float) * FILTER_STEP
    # each step's share of the kernel, taken at its middle; the tail beyond the span at its start
    w: FloatArray = np.exp(-edges / tc) * (1.0 - math.exp(-FILTER_STEP / tc))
    w[-1] = math.exp(-edges[-1] / tc)
    lags: FloatArray = edges + 0.5 * FILTER_STEP
    lags[-1] = edges[-1]
    lags.setflags(write=False)  # shared: built once per time constant, not every tick
    w.setflags(write=False)
    return lags, w


def filtered_accel(traj: Trajectory, t: float, tc: float) -> FloatArray:
    """The plan's acceleration low-passed with time constant tc at trajectory time t: a function
    of the plan alone (a replan equals its predecessor before its split, so the value does not
    jump at a swap); before the plan's start its start value, past its end rest."""
    lags, w = filter_weights(tc)
    acc = sampler(traj).many(t - lags, 2)
    acc[t - lags >= traj.t_end] = 0.0
    out: FloatArray = w @ acc
    return out


# Terms of the horizontal aim (`[setpoints] aim_horizontal`): (k s², time constant s) each
AimTerms = tuple[tuple[float, float], ...]


def _aim_term(traj: Trajectory, t: float, jet: FloatArray, tc: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """F, F', F'' of one aim term: the plan's acceleration low-passed with time constant tc (0:
    as it is), and its first two derivatives (F' = (a - F) / tc, F'' = (j - F') / tc)."""
    _, _, a, j, s = jet
    if tc <= 0.0:
        return a, j, s
    f = filtered_accel(traj, t, tc)
    df = (a - f) / tc
    return f, df, (j - df) / tc


def sample(traj: Trajectory, t: float, yaw: YawPolicy, accel_lead: float = 0.0, accel_lead_tc: float = 0.0,
           aim_horizontal: AimTerms = ()) -> Setpoint:
    """Position, velocity and acceleration at trajectory time t (clamped to its span).

    `accel_lead` k (s², `[setpoints] accel_lead`): the setpoint is the jet of p + k F instead of
    p, F the plan's acceleration, low-passed with time constant `accel_lead_tc` (0: as it is:
    position + k acceleration, velocity + k jerk, acceleration + k snap). ArduCopter trails the
    plan by about k F beyond its time lag: the acceleration feed-forward is not all used at
    once, and the velocity loop's integrator gives back what it gathered over the following
    second or two (docs/autopilot-limits.md); aiming k F beyond the plan puts it back on it. At
    rest (past the end) the jet is the end point, plus what F has left.

    `aim_horizontal` ((k, tc), ...; `[setpoints] aim_horizontal`): more such terms, in the
    horizontal plane only (PX4 SIH trails by a sum of two, docs/autopilot-limits.md)."""
    if accel_lead == 0.0 and not aim_horizontal:
        jet = sampler(traj).jet3(t)
        return Setpoint(jet[0], jet[1], jet[2], yaw(jet[1]))
    sm = sampler(traj)
    full = sm.jet(t)
    if t >= sm.t_end:
        full[1:] = 0.0
    p, v, a = full[0].copy(), full[1].copy(), full[2].copy()
    if accel_lead != 0.0:
        f, df, ddf = _aim_term(traj, t, full, accel_lead_tc)
        p, v, a = p + accel_lead * f, v + accel_lead * df, a + accel_lead * ddf
    for k, tc in aim_horizontal:
        f, df, ddf = _aim_term(traj, t, full, tc)
        p[:2] += k * f[:2]
        v[:2] += k * df[:2]
        a[:2] += k * ddf[:2]
    return Setpoint(p, v, a, yaw(full[1]))


# -- the setpoint thread ---------------------------------------------------------------


@dataclass(frozen=True)
class Feed:
    """What the setpoint thread flies: replaced as a whole by the loop, read once per tick."""

    trajectory: Trajectory
    t_base: float  # monotonic instant of trajectory time 0


@dataclass(frozen=True)
class Tick:
    """One wake-up of the setpoint thread, handed to the loop."""

    now: float  # monotonic time of the send (or of the wake-up, if nothing was sent)
    deadline: float
    next_deadline: float
    feed: Feed | None  # what was sampled; None: nothing to send
    setpoint: Setpoint | None
    gap: float | None  # since the previous periodic send, None after a pause
    error: OSError | None = None


log = logging.getLogger("companion")


THREAD_STALL = 0.5  # s: the setpoint thread waking this late stalled (PX4's COM_OF_LOSS_T is 1 s)


class Liveness:
    """The event loop's pulse as the setpoint sender sees it, and the sender's latch.

    The loop `beat()`s every setpoint period. Before each send the sender checks that the last
    beat is at most `limit` old and that it itself woke within THREAD_STALL of its previous
    tick; if either fails, the companion stalled: the sender withholds setpoints (`withheld`,
    latched) until the loop, awake again, has decided what to do and calls `release()`. So no
    setpoint of a plan the loop could not supervise leaves after a stall, and the autopilot
    never re-enters OFFBOARD on one (PX4 does, on resumed setpoints, while OFFBOARD is still
    the user's mode). A loop stall alone does not starve the autopilot (the sender keeps
    sending until `limit`), so `limit` may be longer than THREAD_STALL.

    The pulse and the latch live in shared memory with a process-shared lock, so the sender may
    be a thread of the service or a process of its own (companion.sendproc); CLOCK_MONOTONIC,
    which `time.monotonic` reads, is one clock for every process of the machine.
    """

    # slots of the shared array
    _STAMP, _SENT, _HELD, _SINCE, _KIND, _STALL = range(6)
    _KINDS = ("loop", "thread")

    def __init__(self, limit: float, clock: Callable[[], float] = time.monotonic) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.limit = limit
        self.clock = clock
        self._v: Any = ctx.RawArray("d", 6)
        self._lock: Any = ctx.Lock()
        self._v[self._STAMP] = clock()
        self._v[self._SENT] = -math.inf

    @property
    def stamp(self) -> float:
        return float(self._v[self._STAMP])

    @stamp.setter
    def stamp(self, value: float) -> None:
        self._v[self._STAMP] = value

    @property
    def last_sent(self) -> float:
        """When the sender last let a setpoint leave."""
        return float(self._v[self._SENT])

    @property
    def withheld(self) -> tuple[float, str, float] | None:
        """(since, "loop" | "thread", stall s) while setpoints are withheld."""
        with self._lock:
            return self._held()

    def _held(self) -> tuple[float, str, float] | None:
        v = self._v
        if not v[self._HELD]:
            return None
        return (float(v[self._SINCE]), self._KINDS[int(v[self._KIND])], float(v[self._STALL]))

    def beat(self) -> float:
        """On the loop: stamp it alive; returns the time since the previous beat."""
        now = self.clock()
        gap = now - self._v[self._STAMP]
        self._v[self._STAMP] = now
        return float(gap)

    def stale(self, now: float | None = None) -> bool:
        """The loop has not beaten for longer than `limit` (it is stalled, or just woke)."""
        return bool((self.clock() if now is None else now) - self._v[self._STAMP] > self.limit)

    def check(self, now: float, thread_gap: float) -> bool:
        """In the sender, before a send: True when setpoints may leave."""
        v = self._v
        with self._lock:
            if not v[self._HELD]:
                loop_gap = now - v[self._STAMP]
                if loop_gap > self.limit:
                    v[self._SINCE], v[self._KIND], v[self._STALL], v[self._HELD] = now, 0, loop_gap, 1
                elif thread_gap > THREAD_STALL:
                    v[self._SINCE], v[self._KIND], v[self._STALL], v[self._HELD] = now, 1, thread_gap, 1
                else:
                    v[self._SENT] = now
            return not v[self._HELD]

    def release(self) -> tuple[float, str, float] | None:
        """On the loop, once it has dealt with the stall: setpoints may leave again."""
        with self._lock:
            was = self._held()
            self._v[self._HELD] = 0
        return was


class SetpointSender:
    """Periodic setpoints from a thread of their own, on absolute deadlines.

    On the event loop, a tick waits for whatever callback runs when its deadline comes (Zenoh
    traffic, MAVLink decoding, status, a plan's result) and for the loop's timer (1 ms
    granularity plus a spin). This thread instead sleeps in `time.sleep`, which CPython (>=
    3.11) implements with clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME), samples the feed,
    sends, and hands the tick to the loop (`on_tick`, called from this thread: it must only
    schedule work on the loop) for statistics, state changes and garbage collection, so the
    thread does a sample and a send a tick (~0.1 ms; ~0.5 ms of CPU with the wake-up on the
    development VM). It still needs the GIL: the short switch interval the service sets
    bounds how long another thread can keep it.

    `priority` > 0: the thread asks for SCHED_FIFO at that priority (CAP_SYS_NICE or
    RLIMIT_RTPRIO); a thread already under SCHED_FIFO/RR (see companion.rtsched) keeps it.
    """

    def __init__(self, rate: float, send: Callable[[Setpoint], None], yaw: YawPolicy,
                 on_tick: Callable[[Tick], None], on_failure: Callable[[BaseException], None],
                 priority: int = 0, clock: Callable[[], float] = time.monotonic) -> None:
        self.rate = rate
        self.send = send
        self.yaw = yaw
        self.on_tick = on_tick
        self.on_failure = on_failure
        self.priority = priority
        self.clock = clock
        self.feed: Feed | None = None
        self.liveness: Liveness | None = None  # None: no stall check (unit tests)
        self.lead = 0.0  # s: setpoints are sampled this far ahead on the trajectory (lag compensation)
        self.accel_lead = 0.0  # s²: see `sample`
        self.accel_lead_tc = 0.0  # s: see `sample`
        self.aim_horizontal: AimTerms = ()  # see `sample`
        self.scheduling = "normal"  # as the thread found or set it, for the logs and status
        self.native_id: int | None = None
        self._stop = threading.Event()
        self._running = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, starter: Callable[[Callable[[], None]], threading.Thread] | None = None) -> None:
        """Start the thread (by `starter`, e.g. companion.rtsched's reserved realtime thread);
        returns once it runs, its scheduling settled."""
        if starter is not None:
            self._thread = starter(self._main)
        else:
            self._thread = threading.Thread(target=self._main, name="setpoints", daemon=True)
            self._thread.start()
        self._running.wait(5.0)

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)

    def _main(self) -> None:
        self.native_id = threading.get_native_id()
        name_thread("setpoints")
        self.scheduling = realtime_here(self.priority)
        self._running.set()
        try:
            self._run()
        except Exception as exc:  # a bug: the service stops (and systemd restarts it)
            log.critical("the setpoint thread failed", exc_info=True)
            self.on_failure(exc)

    @property
    def withheld(self) -> bool:
        """Setpoints are withheld after a stall (see Liveness) until the loop releases them."""
        return self.liveness is not None and self.liveness.withheld is not None

    def _run(self) -> None:
        sched = DeadlineScheduler(self.clock(), self.rate)
        last: float | None = None
        woke = self.clock()
        while not self._stop.is_set():
            deadline = sched.next_deadline(self.clock())
            delay = deadline - self.clock()
            if delay > 0:
                time.sleep(delay)
            now = self.clock()
            thread_gap, woke = now - woke, now
            feed = self.feed
            # A stall after a setpoint left is latched even when the stream was released
            # meanwhile: the autopilot may have left OFFBOARD for want of setpoints, and the loop,
            # first to run after the stall, seen that and released control; the stall is still
            # the cause, and is said (companion.stalls).
            if self.liveness is not None and (feed is not None or (last is not None and thread_gap > THREAD_STALL)) \
                    and not self.liveness.check(now, thread_gap):
                feed = None
            gap = error = sp = None
            if feed is not None:
                sp = sample(feed.trajectory, now - feed.t_base + self.lead, self.yaw, self.accel_lead, self.accel_lead_tc,
                            self.aim_horizontal)
                try:
                    self.send(sp)
                except OSError as exc:  # reported on the loop; the next tick tries again
                    error = exc
                gap = None if last is None else now - last
                last = now
            else:
                last = None
            self.on_tick(Tick(now, deadline, sched.deadline(sched.k + 1), feed, sp, gap, error))


def name_thread(name: str) -> None:
    """The OS-level name of the calling thread (`top -H`, /proc/PID/task/TID/comm), Linux
    only, best effort (written to procfs: ctypes would cost the process ~0.5 MB)."""
    with contextlib.suppress(OSError), open("/proc/thread-self/comm", "w") as f:
        f.write(name[:15])


def realtime_here(priority: int) -> str:
    """Put the calling thread under SCHED_FIFO `priority` (> 0) if permitted; say what it runs under."""
    try:
        policy = os.sched_getscheduler(0)
        if policy in (os.SCHED_FIFO, os.SCHED_RR):
            return f"{'fifo' if policy == os.SCHED_FIFO else 'rr'} {os.sched_getparam(0).sched_priority}"
        if priority <= 0:
            return "normal"
        os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(priority))
        return f"fifo {priority}"
    except (OSError, AttributeError) as exc:
        log.warning("realtime_priority %d not applied to the setpoint thread (%s); it runs with normal "
                    "scheduling", priority, exc)
        return "normal"
