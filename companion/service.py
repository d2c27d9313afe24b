"""The companion service: one asyncio loop per vehicle.

Zenoh in (mission, obstacles, change, command) -> validation -> planning in a
worker thread -> verified trajectory -> absolute-deadline setpoint thread ->
MAVLink out. Telemetry comes back over MAVLink and goes out on Zenoh.

Invariants:
- the setpoint thread samples `self.active`, which is only ever a verified
  trajectory or a hold at a measured position;
- a swap replaces `self.active` with a trajectory equal to the old one up to
  the split time (checked), so the piece being flown never changes;
- trajectory time is `time.monotonic() - self.t_base`, fixed while we keep
  control; replans keep it;
- after a pop-up obstacle on the flown path, either a verified replan is swapped
  in or, by the braking deadline (time to hit minus a stop and a margin), a
  verified stop planned in parallel; a nearer pop-up meanwhile brings the
  deadline forward.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import json
import logging
import logging.handlers
import math
import multiprocessing
import os
import queue
import sys
import time
from collections.abc import Callable
from concurrent.futures import BrokenExecutor, Executor, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from companion import route as rt
from companion import rtsched
from companion.config import Config
from companion.flight import (
    AIRBORNE_CONTROL,
    IN_OUR_MODE,
    Flight,
    State,
    on_mode_report,
    refuse_command,
)
from companion.frames import change_to_ned, obstacles_to_ned, scenario_to_ned
from companion.mavlink_io import CommandFailed, MavlinkLink
from companion.messages import MessageError, decode, warm_validators
from companion.sdnotify import Notifier
from companion.setpoints import (
    DeadlineScheduler,
    Feed,
    GcPacer,
    Setpoint,
    SetpointSender,
    Tick,
    YawPolicy,
    hold_trajectory,
    sample,
    sampler,
    sleep_until,
)
from companion.zenoh_io import ZenohIO, encode
from planner_core import plan
from planner_core.changes import AddObstacles
from planner_core.io import trajectory_to_dict
from planner_core.problem import Polytope, Problem, Trajectory, rest_jet

log = logging.getLogger("companion")

S = State
MAV_LANDED_IN_AIR = 2
INLINE_DECODE_BYTES = 4096
# A stop planned for "now" starts this far ahead at least (its QPs take 15-30 ms).
BRAKE_LEAD = 0.08
# Start preparing the stop this long before the braking deadline if the replan is still out.
BRAKE_PREPARE = 0.35


def _r(x: float | None, nd: int = 4) -> float | None:
    return None if x is None or not math.isfinite(x) else round(float(x), nd)


def _vec(v: Any) -> list[float] | None:
    a = np.asarray(v, dtype=float)
    return None if not np.all(np.isfinite(a)) else [round(float(x), 4) for x in a]


def trajectory_dict(traj: Trajectory) -> dict[str, Any]:
    return trajectory_to_dict(traj, "ned")


def encode_trajectory(traj: Trajectory) -> bytes:
    """Trajectory JSON, one segment per json.dumps call so other threads get the GIL between."""
    head = trajectory_to_dict(Trajectory(traj.times[:2], traj.control_points[:1], None, traj.stats), "ned")
    head["segments"] = []
    parts = []
    corridors = traj.corridors or (None,) * traj.n_segments
    for s in range(traj.n_segments):
        c = corridors[s]
        parts.append(json.dumps({
            "t0": float(traj.times[s]), "t1": float(traj.times[s + 1]),
            "control_points": traj.control_points[s].tolist(),
            "corridor": None if c is None else {"A": c.A.tolist(), "b": c.b.tolist()},
        }, separators=(",", ":")))
    text = json.dumps(head, separators=(",", ":"), default=str)
    return text.replace('"segments":[]', '"segments":[' + ",".join(parts) + "]", 1).encode()


@dataclass(frozen=True)
class Replanned:
    ok: bool
    reason: str = ""
    blocked: int | None = None  # mission index of a blocked waypoint
    blocked_message: str = ""


class StopGuard:
    """A verified stop, planned (once started) for the braking deadline in the brake thread."""

    def __init__(self, svc: Service, base: Trajectory, deadline: float, hit: float) -> None:
        self.svc = svc
        self.base = base
        self.deadline = deadline
        self.hit = hit
        self.notes: list[str] = []
        self.future: asyncio.Future[rt.StopPlan] | None = None

    def tighten(self, deadline: float, hit: float, why: str) -> None:
        """Another obstacle, nearer, arrived during the race: brake for it in time."""
        if deadline >= self.deadline:
            return
        self.deadline, self.hit = deadline, min(self.hit, hit)
        self.notes.append(why)
        plan = self.ready()
        if self.future is not None and (plan is None or plan.trajectory is None or plan.start > deadline):
            self.future.cancel()  # planned for the later deadline (or still planning for it)
            self.future = None

    def start(self) -> None:
        if self.future is None:
            self.future = self.svc.stop_future(self.base, [self.deadline])

    def ready(self) -> rt.StopPlan | None:
        f = self.future
        if f is None or not f.done() or f.cancelled() or f.exception() is not None:
            return None
        return f.result()

    def start_time(self) -> float:
        """When the stop starts: planned, or the deadline while it is not known yet."""
        plan = self.ready()
        return self.deadline if plan is None or plan.trajectory is None else plan.start

    async def result(self) -> rt.StopPlan | None:
        self.start()
        assert self.future is not None
        try:
            return await self.future
        except Exception as exc:  # a planner bug: the caller falls back to a fresh stop
            log.exception("stop planning failed: %r", exc)
            return None

    def cancel(self) -> None:
        if self.future is not None:
            self.future.cancel()


class Service:
    def __init__(self, cfg: Config, stop: asyncio.Event | None = None) -> None:
        self.cfg = cfg
        self.stop = stop or asyncio.Event()
        self.flight = Flight()
        self.link = MavlinkLink(cfg, self._on_mavlink)
        self.zio: ZenohIO | None = None
        self.pool: Executor = make_planner_pool(cfg)
        # Replans and braking never queue behind a long mission plan: their own worker.
        self.urgent_pool: Executor = make_planner_pool(cfg, workers=1, nice=URGENT_NICE)
        # Local replans take a few ms: run them in this process (a thread; the short GIL
        # switch interval keeps the setpoint thread on time) rather than pay the process pool's
        # pickling and hand-offs, which cost more than the replan itself.
        self.replan_pool = ThreadPoolExecutor(1, thread_name_prefix="replan")
        self.io_pool = ThreadPoolExecutor(1, thread_name_prefix="encode")
        self.decode_pool = ThreadPoolExecutor(1, thread_name_prefix="decode")
        # Stops are planned here, never behind a replan (in the urgent process) that may be
        # what is late: two threads, so a fresh stop need not wait for a prepared one.
        self.brake_pool = ThreadPoolExecutor(2, thread_name_prefix="brake")
        self.gc = GcPacer()
        self._traj_seq = 0
        self._traj_published = 0
        self._traj_bytes: bytes | None = None
        self.notifier = Notifier()
        self.yaw = YawPolicy(cfg.setpoints.yaw_mode, cfg.setpoints.yaw, cfg.setpoints.yaw_min_speed)
        self.loop: asyncio.AbstractEventLoop | None = None
        # control (the three properties below feed the setpoint thread)
        self._streaming = False
        self._t_base: float | None = None
        self._active: Trajectory | None = None
        self.sender = SetpointSender(cfg.setpoints.rate_hz, self.link.send_setpoint, self.yaw,
                                     self._tick_from_thread, self._sender_failed,
                                     priority=cfg.setpoints.realtime_priority)
        self._sender_failure: asyncio.Future[None] | None = None
        self.route: rt.Route | None = None
        self.pending: rt.MissionSpec | None = None
        self.obstacles: dict[str, Polytope] = {}
        self.exit_requested = False
        self.disarm_requested = False
        self.airborne = False
        self.link_lost = False
        self.seen_link = False
        self.task: asyncio.Task[None] | None = None
        self.plan_lock = asyncio.Lock()
        self.tasks: list[asyncio.Task[Any]] = []
        # measurements
        self.last_sp: Setpoint | None = None
        self.last_sp_time = 0.0
        self.tracking_error: float | None = None
        self.plan_latency: float | None = None
        self.replan_latency: float | None = None
        self.setpoint_latency: float | None = None
        self._latency_mark: tuple[float, Trajectory, str] | None = None
        self.setpoint_gap_max = 0.0
        self.periods: collections.deque[float] = collections.deque(maxlen=1000)
        self._status_dirty = True
        self._in_start = False
        self._ordered: asyncio.Queue[tuple[str, bytes, float]] = asyncio.Queue()
        self._ticked = asyncio.Event()
        self._race: StopGuard | None = None  # the replan racing a braking deadline, if any
        self._log_listener: logging.handlers.QueueListener | None = None

    # -- what the setpoint thread flies ------------------------------------------

    @property
    def streaming(self) -> bool:
        return self._streaming

    @streaming.setter
    def streaming(self, value: bool) -> None:
        self._streaming = value
        self._feed()

    @property
    def t_base(self) -> float | None:
        return self._t_base

    @t_base.setter
    def t_base(self, value: float | None) -> None:
        self._t_base = value
        self._feed()

    @property
    def active(self) -> Trajectory | None:
        return self._active

    @active.setter
    def active(self, value: Trajectory | None) -> None:
        self._active = value
        self._feed()

    def _feed(self) -> None:
        """One immutable snapshot for the setpoint thread, replaced in one assignment, so it
        never samples one trajectory on another's time base."""
        a, t = self._active, self._t_base
        self.sender.feed = Feed(a, t) if self._streaming and a is not None and t is not None else None

    # -- small helpers -------------------------------------------------------

    def now_t(self) -> float:
        assert self.t_base is not None
        return time.monotonic() - self.t_base

    def event(self, kind: str, message: str, **extra: Any) -> None:
        body = {"type": kind, "time": round(time.time(), 3), "state": self.flight.state.value, "message": message, **extra}
        log.info("%s: %s %s", kind, message, {k: v for k, v in extra.items() if k != "trajectory"})
        if self.zio is not None:
            try:
                self.zio.publish("events", body)
            except Exception as exc:  # never let a publish error reach the flight logic
                log.warning("event publish failed: %s", exc)
        self._status_dirty = True

    def go(self, to: State, reason: str) -> None:
        ev = self.flight.go(to, reason)
        if ev is not None:
            self.event("state", reason, **{"from": ev["from"], "to": ev["to"]})

    def reject(self, key: str, field: str, reason: str, **extra: Any) -> None:
        self.event("rejected", f"{key}: {field + ': ' if field else ''}{reason}", key=key, field=field, reason=reason, **extra)

    async def in_pool(self, fn: Any, *args: Any, urgent: bool = False) -> Any:
        assert self.loop is not None
        try:
            return await self.loop.run_in_executor(self.urgent_pool if urgent else self.pool, fn, *args)
        except BrokenExecutor:
            # The planner process died (OOM, signal): start a fresh one for the next request.
            if urgent:
                self.urgent_pool = make_planner_pool(self.cfg, workers=1, nice=URGENT_NICE)
            else:
                self.pool = make_planner_pool(self.cfg)
            self.event("error", "the planner process died; restarted it (this request failed)")
            raise

    async def loop_run(self, pool: Executor, fn: Any, *args: Any) -> Any:
        assert self.loop is not None
        return await self.loop.run_in_executor(pool, fn, *args)

    def obstacle_list(self) -> list[Polytope]:
        return list(self.obstacles.values())

    # -- control primitives --------------------------------------------------

    def take_control(self, position: np.ndarray, reason: str) -> None:
        """Start streaming a hold at a measured position, with a fresh time base."""
        self.streaming = False  # no tick may pair the old plan with the new time base
        self.t_base = time.monotonic()
        self.yaw.reset(float(self.link.state.attitude[2]))
        self.active = hold_trajectory(position, 0.0)
        self.exit_requested = False
        self.streaming = True
        self.publish_trajectory()
        log.info("taking control: %s", reason)

    def release_control(self) -> None:
        """Stop commanding at once; remember what is left of the mission for `start`."""
        self.streaming = False
        if self.route is not None and self.t_base is not None:
            remaining = self.remaining_mission(self.now_t())
            if remaining is not None:
                self.pending = remaining
        self.route = None
        self.active = None
        self.t_base = None
        if self.task is not None and self.task is not asyncio.current_task() and not self.task.done():
            self.task.cancel()

    def remaining_mission(self, t: float) -> rt.MissionSpec | None:
        r = self.route
        if r is None:
            return None
        keep = (r.times > t) & (r.labels >= 0)
        if not np.any(keep):
            return None
        wps = r.waypoints[keep]
        return replace(r.mission, waypoints=wps, durations=None, start="current", initial=None)

    def swap(self, new: Trajectory, t_split: float, arrived: float | None, what: str) -> bool:
        """Atomically replace the active trajectory; the new one must equal the old before t_split."""
        old = self.active
        if old is not None and self.t_base is not None:
            now = self.now_t()
            if t_split <= now + 0.5 / self.cfg.setpoints.rate_hz:
                return False
            # single-time samplers: Trajectory.evaluate/jet cost ~0.5 ms a call, on the
            # pop-up's critical path
            so, sn = sampler(old), sampler(new)
            ts = np.linspace(now, t_split, 8)
            if not np.allclose([so.jet(t)[0] for t in ts], [sn.jet(t)[0] for t in ts], atol=1e-6):
                log.error("swap refused: new trajectory differs from the flown one before the split")
                return False
            jo, jn = so.jet(t_split), sn.jet(t_split)
            if not np.allclose(jo, jn, rtol=1e-6, atol=1e-6):
                log.error("swap refused: jets differ at the split")
                return False
            new = rt.trim_before(new, now - 1.0)
        self.active = new
        if arrived is not None:
            self._latency_mark = (arrived, new, what)
        self.send_now()
        self.publish_trajectory()
        return True

    def send_now(self) -> None:
        """One setpoint from the active trajectory at once, off the periodic grid (which is
        kept as it is): a new plan reaches the autopilot without waiting up to a period for
        the next tick. The periodic statistics ignore it."""
        if not self.streaming or self.active is None or self.t_base is None:
            return
        now = time.monotonic()
        try:
            self.link.send_setpoint(sample(self.active, now - self.t_base, self.yaw))
        except OSError as exc:  # the periodic loop reports a dead link; never fail a swap on it
            log.warning("immediate setpoint not sent: %s", exc)
            return
        self._report_latency(now, immediate=True)

    def _report_latency(self, now: float, immediate: bool, sampled: Trajectory | None = None) -> None:
        mark = self._latency_mark
        if mark is None or mark[1] is not (self.active if sampled is None else sampled):
            return
        self._latency_mark = None
        self.setpoint_latency = now - mark[0]
        # sent_mono: CLOCK_MONOTONIC at the send (shared by every process on this machine), so a
        # benchmark can find this setpoint in a capture and leave it out of period statistics.
        self.event("latency", f"{mark[2]}: first setpoint of the new plan "
                   f"{self.setpoint_latency * 1000:.1f} ms after the message",
                   what=mark[2], latency_ms=round(self.setpoint_latency * 1000, 2),
                   immediate=immediate, sent_mono=round(now, 6))

    def publish_trajectory(self) -> None:
        """Encode off the loop (json.dumps of a long plan holds the GIL), then publish."""
        if self.zio is None or self.active is None or self.loop is None:
            return
        self._traj_seq += 1
        seq, traj = self._traj_seq, self.active
        fut = self.loop.run_in_executor(self.io_pool, encode_trajectory, traj)

        def done(f: asyncio.Future[bytes]) -> None:
            if f.cancelled() or f.exception() is not None or seq < self._traj_published:
                return
            self._traj_published = seq
            self._traj_bytes = f.result()
            if self.zio is not None:
                self.zio.publish_bytes("trajectory", self._traj_bytes)

        fut.add_done_callback(done)

    # -- loops -----------------------------------------------------------------

    def _tick_from_thread(self, tick: Tick) -> None:
        """Called by the setpoint thread after each tick: the rest happens on the loop."""
        loop = self.loop
        if loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop is closing
                loop.call_soon_threadsafe(self._on_tick, tick)

    def _sender_failed(self, exc: BaseException) -> None:
        loop, fut = self.loop, self._sender_failure
        if loop is None or fut is None:
            return

        def fail() -> None:
            if not fut.done():
                fut.set_exception(RuntimeError(f"the setpoint thread failed: {exc!r}"))

        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(fail)

    def _on_tick(self, tick: Tick) -> None:
        """Bookkeeping of one setpoint tick, on the loop, right after the send."""
        # Both the thread and the loop must be alive for systemd's watchdog to be fed.
        self.notifier.watchdog()
        if tick.error is not None:
            log.warning("setpoint not sent: %s", tick.error)
        feed = tick.feed
        if feed is not None and tick.setpoint is not None:
            if tick.gap is not None:
                self.periods.append(tick.gap)
                self.setpoint_gap_max = max(self.setpoint_gap_max, tick.gap)
                if tick.gap > 0.04:
                    log.warning("setpoint gap %.1f ms (deadline late by %.1f ms)", tick.gap * 1000,
                                (tick.now - tick.deadline) * 1000)
            self.last_sp, self.last_sp_time = tick.setpoint, tick.now
            self._report_latency(tick.now, immediate=False, sampled=feed.trajectory)
            if feed.trajectory is self.active and feed.t_base == self.t_base:
                self._progress(tick.now - feed.t_base)
        else:
            self.last_sp = None
        # Right after a send, the most slack until the next deadline: collect here, never
        # wherever an allocation (in any thread) would have triggered it.
        self.gc.after_send(time.monotonic(), tick.next_deadline)
        self._ticked.set()  # wakes the waiters in after_tick(); they run once we sleep
        self._ticked.clear()
        if self.gc.last is not None:
            gen, took = self.gc.last
            self.gc.last = None
            if took > 0.003:
                log.warning("garbage collection (generation %d) took %.1f ms", gen, took * 1000)

    def _progress(self, t: float) -> None:
        st = self.flight.state
        if st is S.STREAMING and self.route is not None and t >= self.route.t_end:
            self.go(S.HOLDING, f"mission {self.route.mission.id} complete: holding at the last waypoint")
            self.event("mission_complete", f"mission {self.route.mission.id} complete", mission=self.route.mission.id)
        elif st is S.BRAKING and self.active is not None and t >= self.active.t_end:
            self.go(S.HOLDING, "stopped after braking: holding position")

    async def heartbeat_loop(self) -> None:
        sched = DeadlineScheduler(time.monotonic(), self.cfg.mavlink.heartbeat_hz)
        while not self.stop.is_set():
            with contextlib.suppress(OSError):
                self.link.send_heartbeat()
            self.check_link()
            await sleep_until(sched.next_deadline(time.monotonic()), spin=0.0)

    async def after_tick(self) -> None:
        """Wait for the moment right after the next setpoint tick, when the next deadline is
        furthest away: periodic publishing done then cannot make a setpoint late."""
        await self._ticked.wait()

    async def telemetry_loop(self) -> None:
        sched = DeadlineScheduler(time.monotonic(), 20.0)
        while not self.stop.is_set():
            await sleep_until(sched.next_deadline(time.monotonic()), spin=0.0)
            await self.after_tick()
            st = self.link.state
            if st.has_position and self.zio is not None:
                self.zio.publish("telemetry", {
                    "time": round(time.time(), 3),
                    "frame": "ned",
                    "position": _vec(st.position),
                    "velocity": _vec(st.velocity),
                    "attitude": {"roll": _r(st.attitude[0]), "pitch": _r(st.attitude[1]), "yaw": _r(st.attitude[2])},
                    "armed": st.armed,
                    "mode": st.mode,
                })
            self.check_link()

    async def status_loop(self) -> None:
        last = 0.0
        while not self.stop.is_set():
            await asyncio.sleep(0.05)
            await self.after_tick()
            now = time.monotonic()
            if self._status_dirty or now - last >= 0.5:
                self._status_dirty = False
                last = now
                if self.zio is not None:
                    self.zio.publish("status", self.status())

    def status(self) -> dict[str, Any]:
        st = self.link.state
        seg = progress = time_to_go = None
        if self.route is not None and self.t_base is not None:
            t = self.now_t()
            r = self.route
            i = int(np.clip(np.searchsorted(r.times, t, side="right") - 1, 0, len(r.times) - 2))
            nxt = r.labels[i + 1:]
            ahead = nxt[nxt >= 0]
            seg = int(ahead[0]) - 1 if len(ahead) else int(np.max(r.labels))
            progress = float(np.clip((t - r.times[0]) / max(r.t_end - r.times[0], 1e-9), 0.0, 1.0))
            time_to_go = max(r.t_end - t, 0.0)
        if self.streaming and self.active is not None and st.has_position and self.t_base is not None:
            ref = sampler(self.active).jet(self.now_t())[0]
            self.tracking_error = float(np.linalg.norm(st.position - ref))
        elif not self.streaming:
            self.tracking_error = None
        return {
            "vehicle": self.cfg.vehicle.id,
            "time": round(time.time(), 3),
            "state": self.flight.state.value,
            "autopilot": st.autopilot,
            "mode": st.mode,
            "armed": st.armed,
            "link": self.link.link_ok() if self.seen_link else False,
            "streaming": self.streaming,
            "mission": None if self.route is None else self.route.mission.id,
            "pending_mission": None if self.pending is None else self.pending.id,
            "segment": seg,
            "progress": _r(progress),
            "time_to_go": _r(time_to_go, 3),
            "tracking_error": _r(self.tracking_error),
            "plan_latency_ms": _r(None if self.plan_latency is None else self.plan_latency * 1000, 2),
            "replan_latency_ms": _r(None if self.replan_latency is None else self.replan_latency * 1000, 2),
            "message_to_setpoint_ms": _r(None if self.setpoint_latency is None else self.setpoint_latency * 1000, 2),
            "obstacles": sorted(self.obstacles),
            "setpoints_sent": self.link.sent_setpoints,
            "setpoint_gap_max_ms": round(self.setpoint_gap_max * 1000, 2),
            "setpoint_period_ms": period_stats(self.periods),
            "gc_pause_max_ms": round(self.gc.worst * 1000, 2),
        }

    # -- autopilot reports ---------------------------------------------------

    def _on_mavlink(self, kind: str, msg: Any) -> None:
        if kind == "HEARTBEAT":
            self.on_heartbeat()
        elif kind == "STATUSTEXT":
            self.event("autopilot", f"autopilot says: {msg.text}", severity=int(msg.severity))

    def on_heartbeat(self) -> None:
        st = self.link.state
        if not self.seen_link:
            self.seen_link = True
            self.event("link", f"autopilot found: {st.autopilot} in {st.mode}", autopilot=st.autopilot, mode=st.mode)
        if self.link_lost:
            self.link_lost = False
            self.event("link_restored", f"MAVLink link restored: autopilot in {st.mode}, "
                       f"{'armed' if st.armed else 'disarmed'}; send 'start' to take control again",
                       mode=st.mode, armed=st.armed)
        state = self.flight.state
        reaction = on_mode_report(state, st.in_follow_mode(), self.exit_requested)
        if reaction is not None:
            self.release_control()
            self.go(reaction[0], f"{reaction[1]} (mode {st.mode})")
            self.event("pilot_takeover", f"autopilot switched to {st.mode}: stopped commanding; "
                       "send 'start' to take control again", mode=st.mode)
            return
        if state in IN_OUR_MODE and not st.armed and not self.disarm_requested:
            self.release_control()
            self.airborne = False
            self.go(S.IDLE, "the autopilot disarmed the vehicle")
            self.event("failsafe", "the autopilot disarmed the vehicle", mode=st.mode)
        elif state is S.LANDING and not st.armed:
            self.airborne = False
            self.go(S.IDLE, "landed and disarmed")
        if st.landed_state == MAV_LANDED_IN_AIR:
            self.airborne = True
        self._status_dirty = True

    def check_link(self) -> None:
        if not self.seen_link or self.link_lost or self.link.link_ok():
            return
        self.link_lost = True
        was = self.flight.state
        if self.flight.controlling:
            self.release_control()
            self.go(S.FAILSAFE, "MAVLink link lost: no autopilot heartbeat")
        self.event("link_lost", f"MAVLink link lost (no heartbeat for {self.cfg.mavlink.link_timeout} s) while {was.value}; "
                   "stopped commanding", previous_state=was.value)

    # -- inbound messages -------------------------------------------------------

    async def inbox_loop(self) -> None:
        """Small obstacle messages (pop-ups) are handled at once; the rest keep their order in
        `ordered_loop`, where one large mission may take a while to validate: a pop-up must not
        wait behind it. (Obstacle updates do not depend on a mission being loaded first: a
        mission is planned against the obstacles known when it is planned.)"""
        assert self.zio is not None
        while not self.stop.is_set():
            kind, payload, arrived = await self.zio.inbox.get()
            if kind == "obstacles" and len(payload) <= INLINE_DECODE_BYTES:
                self._dispatch(kind, payload, arrived, self._decode(kind, payload))
            else:
                self._ordered.put_nowait((kind, payload, arrived))

    async def ordered_loop(self) -> None:
        while not self.stop.is_set():
            kind, payload, arrived = await self._ordered.get()
            job = functools.partial(self._decode, kind, payload)
            # JSON Schema validation is pure Python (~0.1 ms per waypoint): large messages off
            # the loop, small ones (a command: well under a millisecond) right here, which
            # spares two thread hand-offs. One message at a time, so the order is kept.
            assert self.loop is not None
            obj = job() if len(payload) <= INLINE_DECODE_BYTES else \
                await self.loop.run_in_executor(self.decode_pool, job)
            self._dispatch(kind, payload, arrived, obj)

    def _decode(self, kind: str, payload: bytes) -> dict[str, Any] | MessageError:
        lim = self.cfg.limits
        try:
            return decode(kind, payload, max_bytes=lim.max_message_bytes,
                          max_waypoints=lim.max_waypoints, max_obstacles=lim.max_obstacles)
        except MessageError as exc:
            return exc

    def _dispatch(self, kind: str, payload: bytes, arrived: float, obj: dict[str, Any] | MessageError) -> None:
        if isinstance(obj, MessageError):
            self.reject(kind, obj.field, obj.reason, bytes=len(payload))
            return
        handler = {"mission": self.on_mission, "obstacles": self.on_obstacles,
                   "change": self.on_change, "command": self.on_command}[kind]
        task = asyncio.create_task(self._guard(kind, handler(obj, arrived)))
        self.tasks.append(task)
        self.tasks = [t for t in self.tasks if not t.done()]

    async def _guard(self, kind: str, coro: Any) -> None:
        try:
            await coro
        except MessageError as exc:
            self.reject(kind, exc.field, exc.reason)
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # a bug in one handler must not stop the service
            log.exception("handler for %s failed", kind)
            self.event("error", f"{kind}: internal error: {exc!r}; holding the current plan", key=kind)

    # mission ---------------------------------------------------------------

    async def on_mission(self, obj: dict[str, Any], arrived: float) -> None:
        spec = rt.mission_from_message(scenario_to_ned(obj), self.cfg)
        if self.flight.state in AIRBORNE_CONTROL and spec.autostart:
            await self.fly(spec, arrived)
            return
        st = self.link.state
        plan_ms = None
        if st.has_position:
            jet = rest_jet(st.position)
            t0 = time.perf_counter()
            # The check only needs the verdict: a 1000-waypoint route coming back would be
            # unpickled here in one GIL-holding call of many milliseconds.
            outcome = await self.in_pool(rt.check_mission, replace(spec, raw={}), jet, 0.0,
                                         self.obstacle_list(), self.cfg)
            plan_ms = round((time.perf_counter() - t0) * 1000, 2)
            if not outcome.ok:
                self._reject_outcome("mission", spec, outcome)
                return
        self.pending = spec
        self.event("accepted", f"mission {spec.id} loaded ({len(spec.waypoints)} waypoints); "
                   "send 'start' to fly it", key="mission", mission=spec.id, plan_ms=plan_ms, pending=True)

    def _reject_outcome(self, key: str, spec: rt.MissionSpec, outcome: rt.Outcome) -> None:
        field = "" if outcome.blocked_waypoint is None else f"waypoints[{outcome.blocked_waypoint}]"
        self.reject(key, field, f"mission {spec.id}: {outcome.message}", mission=spec.id)

    async def fly(self, spec: rt.MissionSpec, arrived: float | None) -> bool:
        """Plan `spec` from the commanded state a little ahead of now and fly it."""
        async with self.plan_lock:
            for attempt in range(3):
                if self.active is None or self.flight.state not in AIRBORNE_CONTROL:
                    self.reject("mission", "", f"mission {spec.id}: no longer in control ({self.flight.state.value})")
                    return False
                base = self.active
                t_split = self.now_t() + self.cfg.planner.split_ahead * (2 ** attempt)
                jet = base.jet(t_split)
                if t_split >= base.t_end:
                    jet[1:] = 0.0
                t0 = time.perf_counter()
                outcome = await self.in_pool(rt.start_mission, replace(spec, raw={}), jet, t_split,
                                             self.obstacle_list(), self.cfg)
                self.plan_latency = time.perf_counter() - t0
                if not outcome.ok or outcome.route is None:
                    self._reject_outcome("mission", spec, outcome)
                    return False
                if self.active is not base or self.flight.state not in AIRBORNE_CONTROL:
                    continue
                if not self.swap(rt.splice(base, outcome.route.trajectory), t_split, arrived, f"mission {spec.id}"):
                    continue
                self.route = outcome.route
                self.pending = None
                self.go(S.STREAMING, f"flying mission {spec.id}")
                self.event("accepted", f"mission {spec.id}: planned and verified in {self.plan_latency * 1000:.1f} ms "
                           f"({len(spec.waypoints)} waypoints, {outcome.route.t_end - t_split:.2f} s)",
                           key="mission", mission=spec.id, plan_ms=round(self.plan_latency * 1000, 2))
                return True
        self.reject("mission", "", f"mission {spec.id}: planning did not finish before its split time")
        return False

    # obstacles -------------------------------------------------------------

    async def on_obstacles(self, obj: dict[str, Any], arrived: float) -> None:
        msg = obstacles_to_ned(obj)
        added: dict[str, Polytope] = {}
        for i, ob in enumerate(msg.get("add", [])):
            added[ob["id"]] = rt.parse_region(ob, f"add[{i}]")
        removed = [k for k in msg.get("remove", []) if k in self.obstacles]
        unknown = [k for k in msg.get("remove", []) if k not in self.obstacles]
        if msg.get("clear"):
            removed = list(self.obstacles)
        for k in removed:
            del self.obstacles[k]
        self.obstacles.update(added)
        note = f"; unknown ids ignored: {unknown}" if unknown else ""
        announce = functools.partial(
            self.event, "accepted", f"obstacles: added {sorted(added)}, removed {sorted(removed)}{note}",
            key="obstacles", added=sorted(added), removed=sorted(removed))
        if added:
            # said once the replan is under way: the event costs time a pop-up does not have
            await self.avoid(list(added.values()), sorted(added), arrived, announce)
        else:
            announce()

    async def avoid(self, new: list[Polytope], ids: list[str], arrived: float,
                    announce: Callable[[], None] = lambda: None) -> None:
        race = self._race
        if race is not None and self.active is race.base and self.route is not None and self.t_base is not None:
            # A replan for an earlier pop-up holds the lock until it is swapped in or its
            # braking deadline: this obstacle may need the stop sooner.
            now = self.now_t()
            hit = rt.first_hit(self.active, now, new, self.route.mission.radius)
            if hit is not None:
                race.tighten(rt.brake_deadline(self.active, now, hit, self.route.mission.bounds), hit,
                             f"deadline brought forward by obstacles {ids} (hit at t={hit:.2f} s)")
        async with self.plan_lock:
            if self.flight.state is not S.STREAMING or self.route is None or self.active is None:
                announce()
                return
            now = self.now_t()
            radius = self.route.mission.radius
            hit = rt.first_hit(self.active, now, new, radius)
            if hit is None or hit < now + self.cfg.planner.split_ahead:
                announce()
            if hit is None:
                self.event("obstacles_clear", f"obstacles {ids}: the current trajectory stays clear; no replan",
                           obstacles=ids)
                return
            split_ahead = self.cfg.planner.split_ahead
            if hit < now + split_ahead:
                await self._brake(f"obstacle {ids} is {hit - now:.2f} s ahead: too close to replan", arrived)
                return
            known = [p for p in self.obstacle_list() if not any(p is q for q in new)]
            known += [p for _, p in self.route.mission.obstacles]
            edit = rt.LocalEdit((rt_add_obstacles(new),), f"avoid obstacles {ids}")
            await self._replan_or_brake(edit, known, arrived, f"obstacles {ids}", hit, announce)

    async def _replan_or_brake(self, edit: rt.LocalEdit, known: list[Polytope], arrived: float, what: str,
                               hit: float, announce: Callable[[], None]) -> None:
        """Race the replan against the braking deadline: the latest start of a stop that ends
        before the flown plan would enter the obstacle. A verified stop is prepared in parallel
        (at once if the deadline is near, else when the local replan fails or runs late) and
        swapped in at its start unless a verified replan was swapped in first."""
        assert self.route is not None and self.active is not None
        base, bounds, now = self.active, self.route.mission.bounds, self.now_t()
        guard = StopGuard(self, base, hit, hit)
        notes: list[str] = []
        replan = asyncio.create_task(self._replan(edit, known, arrived, what, hit=hit, on_fallback=guard.start,
                                                  notes=notes))
        await asyncio.sleep(0)  # the replan is handed to its thread first; the rest overlaps it
        guard.deadline = rt.brake_deadline(base, now, hit, bounds)
        announce()
        self._race = guard
        try:
            await self._race_deadline(guard, replan, notes, arrived, what)
        finally:
            self._race = None

    async def _race_deadline(self, guard: StopGuard, replan: asyncio.Task[Replanned], notes: list[str],
                             arrived: float, what: str) -> None:
        # Swap with a few periods to spare: the loop may be late, and swap() refuses a split
        # less than half a period ahead.
        spare = 2.0 / self.cfg.setpoints.rate_hz
        while not replan.done():
            if self.flight.state not in AIRBORNE_CONTROL:  # e.g. a pilot took over meanwhile
                replan.cancel()
                guard.cancel()
                return
            wake = guard.start_time() - spare
            if guard.future is None:
                wake = min(wake, guard.deadline - BRAKE_PREPARE)
            delay = wake - self.now_t()
            if delay <= 0:
                if guard.future is None:
                    guard.start()
                    continue
                break
            waiting: set[asyncio.Future[Any]] = {replan}
            if guard.future is not None and not guard.future.done():
                waiting.add(guard.future)
            # at most a tick at a time: another pop-up may bring the deadline forward
            await asyncio.wait(waiting, timeout=min(delay, spare / 2), return_when=asyncio.FIRST_COMPLETED)
        if replan.done():
            failed = None if replan.cancelled() else replan.exception()
            if failed is not None:
                log.error("replan failed: %r", failed)
            result = Replanned(False, f"replan error: {failed!r}") if failed is not None else replan.result()
            if result.ok:
                guard.cancel()
                return
            why = (f"{what}: waypoint {result.blocked} is blocked ({result.blocked_message})"
                   if result.blocked is not None else f"{what}: no safe plan ({result.reason})")
            await self._brake(why, arrived, blocked=result.blocked, prepared=guard.ready())
            return
        replan.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await replan
        pending = "; ".join([*notes, *guard.notes, "the replan is still running"])
        await self._brake_at_deadline(guard, guard.hit, arrived,
                                      f"{what}: no verified replan by the braking deadline t={guard.deadline:.2f} s "
                                      f"(the plan enters the obstacle at t={guard.hit:.2f} s; {pending})")

    async def _replan(self, edit: rt.LocalEdit, known: list[Polytope], arrived: float, what: str,
                      hit: float | None = None, remainder: tuple[Any, Any, Any] | None = None,
                      on_fallback: Any = None, notes: list[str] | None = None) -> Replanned:
        """Local replan, then a full replan of the remainder; swapped in if verified. The caller
        holds plan_lock and decides what a failure means (braking, or a rejected change).
        `notes` collects what failed so far, for a caller that gives up waiting."""
        assert self.route is not None
        messages = notes if notes is not None else []
        for attempt in range(3):
            if self.active is None or self.route is None or self.flight.state not in AIRBORNE_CONTROL:
                return Replanned(False, "no longer in control")
            base, route = self.active, self.route
            now = self.now_t()
            t_split = now + self.cfg.planner.split_ahead * (2 ** attempt)
            if hit is not None and t_split >= hit:
                messages.append("too close to the obstacle to replan")
                break
            t0 = time.perf_counter()
            waited = time.monotonic() - arrived
            outcome = await self.loop_run(self.replan_pool, rt.local_replan, route, now, t_split, edit, known, self.cfg)
            method = "local"
            if not outcome.ok:
                messages.append(f"local replan: {outcome.message}")
                if on_fallback is not None:
                    on_fallback()
                obstacles = self.obstacle_list()
                extra = () if remainder is None else remainder
                outcome = await self.in_pool(rt.replan_remainder, route, base, t_split, obstacles, self.cfg,
                                             *extra, urgent=True)
                if self.cfg.planner.fallback_delay > 0:
                    await asyncio.sleep(self.cfg.planner.fallback_delay)
                method = "remainder"
            self.replan_latency = time.perf_counter() - t0
            if not outcome.ok or outcome.route is None:
                messages.append(f"full replan: {outcome.message}")
                if outcome.blocked_waypoint is not None:
                    return Replanned(False, "; ".join(messages), outcome.blocked_waypoint, outcome.message)
                break
            if self.active is not base or self.route is not route:
                continue
            if not self.swap(rt.splice(base, outcome.route.trajectory), t_split, arrived, what):
                messages.append("planning finished after the split time; retrying further ahead")
                continue
            self.route = outcome.route
            if self.flight.state is not S.STREAMING:
                self.go(S.STREAMING, f"replanned: {edit.description}")
            if outcome.stats.get("detour"):
                method = "detour"
            self.event("replanned", f"{edit.description}: {method} replan verified in "
                       f"{self.replan_latency * 1000:.1f} ms, split at t={t_split:.3f} s",
                       method=method, split_time=round(t_split, 4), replan_ms=round(self.replan_latency * 1000, 2),
                       compute_ms=_r(float(outcome.stats.get("plan_seconds", math.nan)) * 1000, 2),
                       before_replan_ms=round(waited * 1000, 2),
                       resolved_jets=outcome.stats.get("resolved_jets"), detour=outcome.stats.get("detour"))
            return Replanned(True)
        return Replanned(False, "; ".join(messages) or "too close")

    def stop_future(self, base: Trajectory, starts: list[float]) -> asyncio.Future[rt.StopPlan]:
        """Plan a verified stop off `base` in the brake thread (see route.plan_stop)."""
        assert self.loop is not None and self.t_base is not None
        t_base = self.t_base
        mission = self.route.mission if self.route is not None else None
        obstacles = self.obstacle_list() + ([p for _, p in mission.obstacles] if mission else [])
        bounds = mission.bounds if mission is not None else rt.bounds_from(None, self.cfg)
        lead = max(BRAKE_LEAD, 3.0 / self.cfg.setpoints.rate_hz)
        return self.loop.run_in_executor(self.brake_pool, rt.plan_stop, base, starts,
                                         lambda: time.monotonic() - t_base, obstacles, mission, bounds, lead)

    def _commit_stop(self, base: Trajectory, plan: rt.StopPlan | None, arrived: float | None) -> bool:
        if plan is None or plan.trajectory is None or self.active is not base:
            return False
        return self.swap(rt.splice(base, plan.trajectory), plan.start, arrived, "braking")

    async def _brake(self, reason: str, arrived: float | None, blocked: int | None = None,
                     prepared: rt.StopPlan | None = None) -> None:
        """Fly a verified stop inside a free corridor, starting as soon as one is planned; else
        the `prepared` one if it still starts ahead; else hold at the measured position. Say why."""
        if self.active is None or self.t_base is None:
            return
        base = self.active
        try:
            plan = await self.stop_future(base, [self.now_t()])
        except Exception as exc:  # a planner bug must still end in a hold, not in flying on
            log.exception("stop planning failed")
            plan = rt.StopPlan(None, self.now_t(), f"stop planning failed: {exc!r}", False)
        why = plan.message
        swapped = self._commit_stop(base, plan, arrived)
        if not swapped and self._commit_stop(base, prepared, arrived):
            assert prepared is not None
            swapped, plan, why = True, prepared, f"{why}; the stop prepared for the braking deadline instead"
        if not swapped:
            self._hold_here()
            why = f"no verified braking trajectory ({why}); holding at the measured position"
        self.go(S.BRAKING, reason)
        self.event("braking", f"{reason}; braking to a stop and holding", reason=reason,
                   blocked_waypoint=blocked, detail=why, **self._stop_fields(plan if swapped else None))

    async def _brake_at_deadline(self, guard: StopGuard, hit: float, arrived: float, reason: str) -> None:
        """The replan is late: swap in the prepared stop (planned for the deadline)."""
        plan = await guard.result()
        swap_time = self.now_t()
        if not self._commit_stop(guard.base, plan, arrived):
            await self._brake(reason + "; the prepared stop was not usable: "
                              + ("none planned" if plan is None else plan.message), arrived)
            return
        assert plan is not None
        self.go(S.BRAKING, reason)
        self.event("braking", f"{reason}; braking to a stop and holding", reason=reason, blocked_waypoint=None,
                   detail=plan.message, deadline=round(guard.deadline, 4), hit_time=round(hit, 4),
                   swap_time=round(swap_time, 4), **self._stop_fields(plan))

    @staticmethod
    def _stop_fields(plan: rt.StopPlan | None) -> dict[str, Any]:
        if plan is None or plan.trajectory is None:
            return {}
        return {"brake_start": round(plan.start, 4), "stop_time": round(plan.trajectory.t_end, 4),
                "stop_position": _vec(plan.trajectory.control_points[-1, -1]), "in_free_space": plan.in_free_space}

    def _hold_here(self) -> None:
        """Hold at the measured position (verified by construction: it does not move)."""
        self.active = hold_trajectory(self.link.state.position, self.now_t())
        self.send_now()
        self.publish_trajectory()

    # change ------------------------------------------------------------------

    async def on_change(self, obj: dict[str, Any], arrived: float) -> None:
        change = change_to_ned(obj)
        if self.route is None or self.flight.state not in AIRBORNE_CONTROL or self.t_base is None:
            raise MessageError("", f"no mission in flight ({self.flight.state.value})")
        async with self.plan_lock:
            assert self.route is not None
            t_split = self.now_t() + self.cfg.planner.split_ahead
            edit = rt.local_edit(self.route, change, t_split)
            remainder = rt.apply_change(self.route, change, t_split, self.cfg)[:3]
            known = self.obstacle_list() + [p for _, p in self.route.mission.obstacles]
            what = f"change ({edit.description})"
            result = await self._replan(edit, known, arrived, what, remainder=remainder)
            if result.ok:
                self.event("accepted", f"change: {edit.description}", key="change")
            else:
                # The current plan is still safe: a change that cannot be planned is refused.
                self.reject("change", "", f"{what}: no verified plan ({result.reason}); the current plan continues")

    # commands ----------------------------------------------------------------

    async def on_command(self, obj: dict[str, Any], arrived: float) -> None:
        cmd = obj["command"]
        st = self.link.state
        has_mission = self.pending is not None or (
            self.route is not None and self.t_base is not None and self.route.t_end > self.now_t())
        why = refuse_command(self.flight.state, cmd, armed=st.armed, auto_arm=self.cfg.safety.auto_arm,
                             has_mission=has_mission)
        if why is None and st.last_heartbeat == -math.inf:
            why = "no autopilot heartbeat yet"
        if why is None and cmd in ("arm", "takeoff", "start") and not st.has_position:
            why = "no position estimate from the autopilot"
        if why is not None:
            self.event("refused", f"command {cmd}: {why}", key="command", command=cmd, reason=why)
            return
        self.event("accepted", f"command {cmd}", key="command", command=cmd)
        altitude = float(obj.get("altitude", self.cfg.safety.takeoff_altitude))
        if cmd in ("arm", "takeoff", "start"):
            if self.task is not None and not self.task.done():
                self.task.cancel()
            if cmd == "arm":
                body = self.cmd_arm()
            elif cmd == "takeoff":
                body = self.cmd_takeoff(altitude)
            else:
                body = self.cmd_start(arrived)
            self.task = asyncio.create_task(self._sequence(cmd, body))
        elif cmd == "hold":
            async with self.plan_lock:
                await self._brake("hold command", arrived)
        elif cmd == "resume":
            await self.cmd_resume(arrived)
        elif cmd == "land":
            await self.cmd_land()
        elif cmd == "abort":
            await self.cmd_abort(arrived)
        elif cmd == "disarm":
            await self.cmd_disarm()

    async def _sequence(self, cmd: str, coro: Any) -> None:
        try:
            await coro
        except CommandFailed as exc:
            self.event("refused", f"command {cmd} failed: {exc}", key="command", command=cmd, reason=str(exc))
            if self.flight.state in (S.ARMING, S.TAKEOFF):
                self.release_control()
                self.go(S.IDLE if not self.link.state.armed else S.FAILSAFE, f"{cmd} failed: {exc}")
        except asyncio.CancelledError:
            pass

    async def _take_follow_mode(self, reason: str) -> None:
        """Stream a hold at the measured position, then ask for OFFBOARD/GUIDED."""
        st = self.link.state
        self.go(S.ARMING, reason)
        if st.autopilot == "px4":
            self.take_control(st.position, reason)
            # PX4 refuses OFFBOARD unless setpoints have been streaming for a while.
            await asyncio.sleep(1.1)
        await self.link.set_follow_mode()
        await self.link.wait_for(lambda s: s.in_follow_mode(), 3.0, "the autopilot to confirm OFFBOARD/GUIDED")
        if st.autopilot != "px4" and self.airborne:
            self.take_control(st.position, reason)

    async def cmd_arm(self) -> None:
        await self._take_follow_mode("arm command")
        self.disarm_requested = False
        await self.link.arm(True)
        await self.link.wait_for(lambda s: s.armed, 3.0, "the autopilot to report armed")
        self.go(S.READY, "armed in " + self.link.state.mode)

    async def cmd_takeoff(self, altitude: float) -> None:
        st = self.link.state
        if not st.armed:
            await self.cmd_arm()
        elif self.flight.state not in (S.READY, S.HOLDING):
            await self._take_follow_mode("takeoff command")
        ground = st.position.copy()
        target = ground + np.array([0.0, 0.0, -altitude])
        self.go(S.TAKEOFF, f"taking off to {altitude:.2f} m")
        tol = self.cfg.safety.arrival_tolerance
        if st.autopilot == "px4":
            await self._px4_climb(target)
        else:
            self.streaming = False
            await self.link.takeoff(altitude)
            await self.link.wait_for(lambda s: s.position[2] <= target[2] + tol, 10.0 + altitude / 0.3,
                                     f"altitude {altitude:.2f} m")
            self.take_control(self.link.state.position, "takeoff complete")
        self.airborne = True
        self.go(S.READY, f"airborne at {altitude:.2f} m: holding")
        if self.pending is not None and self.pending.autostart and not self._in_start:
            await self.fly(self.pending, None)

    async def _px4_climb(self, target: np.ndarray) -> None:
        """A verified vertical climb streamed in OFFBOARD (PX4 has no GUIDED-style takeoff for us)."""
        assert self.active is not None
        base = self.active
        t_split = self.now_t() + self.cfg.planner.split_ahead
        jet = base.jet(t_split)
        bounds = rt.bounds_from(None, self.cfg)
        d = rt.allocate_durations(np.vstack([jet[0], target]), bounds)
        problem = Problem.from_waypoints(np.vstack([jet[0], target]), d, bounds, initial=jet, t0=t_split)
        result = await self.in_pool(plan, problem)
        if not result.ok or result.trajectory is None:
            raise CommandFailed(f"no verified climb: {result.message}")
        if not self.swap(rt.splice(base, result.trajectory), t_split, None, "takeoff"):
            raise CommandFailed("climb planning was too slow")
        tol = self.cfg.safety.arrival_tolerance
        end = result.trajectory.t_end
        await self.link.wait_for(
            lambda s: self.t_base is not None and self.now_t() >= end and abs(s.position[2] - target[2]) <= tol,
            end - self.now_t() + 10.0, "the climb to finish")

    async def cmd_start(self, arrived: float) -> None:
        self._in_start = True
        try:
            await self._start(arrived)
        finally:
            self._in_start = False

    async def _start(self, arrived: float) -> None:
        st = self.link.state
        if not st.armed:
            await self.cmd_takeoff(self.cfg.safety.takeoff_altitude)
        elif self.flight.state in (S.PILOT, S.FAILSAFE, S.IDLE):
            if not self.airborne and st.landed_state != MAV_LANDED_IN_AIR and st.autopilot != "px4":
                raise CommandFailed("vehicle is on the ground: send 'takeoff' first")
            await self._take_follow_mode("start command: taking control")
            self.go(S.READY, f"in control ({self.link.state.mode}): holding")
        elif self.flight.state is S.READY and not self.airborne:
            await self.cmd_takeoff(self.cfg.safety.takeoff_altitude)
        if self.pending is not None:
            await self.fly(self.pending, arrived)
        elif self.route is not None:
            await self.cmd_resume(arrived)

    async def cmd_resume(self, arrived: float) -> None:
        if self.route is None or self.t_base is None:
            self.event("refused", "command resume: no mission to resume", key="command", command="resume")
            return
        async with self.plan_lock:
            t_split = self.now_t() + self.cfg.planner.split_ahead
            if not np.any(self.route.times > t_split):
                self.event("refused", "command resume: the mission is complete", key="command", command="resume")
                return
            spec = self.remaining_mission(t_split)
        if spec is not None:
            await self.fly(spec, arrived)

    async def cmd_land(self) -> None:
        if self.task is not None and not self.task.done():
            self.task.cancel()
        self.exit_requested = True
        self.streaming = False
        self.route = None
        self.active = None
        self.go(S.LANDING, "land command: the autopilot lands")
        try:
            await self.link.land()
        except CommandFailed as exc:
            self.event("refused", f"command land failed: {exc}", key="command", command="land")

    async def cmd_abort(self, arrived: float) -> None:
        if self.task is not None and not self.task.done():
            self.task.cancel()
        self.pending = None
        state = self.flight.state
        if state in AIRBORNE_CONTROL or (state is S.TAKEOFF and self.streaming):
            async with self.plan_lock:
                self.route = None
                await self._brake("abort command", arrived)
        elif state in (S.ARMING, S.TAKEOFF):
            self.release_control()
            self.go(S.IDLE if not self.link.state.armed else S.FAILSAFE, "abort command")
        self.event("aborted", "mission and pending commands cancelled")

    async def cmd_disarm(self) -> None:
        st = self.link.state
        if st.landed_state == MAV_LANDED_IN_AIR:
            self.event("refused", "command disarm: vehicle is in the air (land first)", key="command", command="disarm")
            return
        self.disarm_requested = True
        self.release_control()
        try:
            await self.link.arm(False)
        except CommandFailed as exc:
            self.event("refused", f"command disarm failed: {exc}", key="command", command="disarm")
            return
        self.airborne = False
        self.go(S.IDLE, "disarmed on command")

    # -- queryables -------------------------------------------------------------

    def query_plan(self) -> bytes | None:
        return None if self.active is None else self._traj_bytes

    def query_status(self) -> bytes | None:
        return encode(self.status())

    # -- run ----------------------------------------------------------------------

    async def run(self) -> None:
        self.loop = asyncio.get_running_loop()
        # Log output (a file or journald on a busy disk) is written by a thread of its own.
        self._log_listener = log_off_loop()
        # The loop and the helper threads hold the GIL in pure-Python stretches; a short
        # switch interval bounds how long the setpoint thread can wait for it.
        sys.setswitchinterval(0.0005)
        self.zio = ZenohIO(self.cfg, self.loop)
        self.zio.open({"plan": self.query_plan, "status": self.query_status})
        self.link.open(self.loop)
        # First calls pay for imports and caches; pay them now, not during a flight.
        await asyncio.gather(self.in_pool(rt.warm_up, self.cfg), self.in_pool(rt.warm_up, self.cfg, urgent=True))
        await self.loop.run_in_executor(self.io_pool, encode_trajectory, hold_trajectory(np.zeros(3), 0.0))
        await self.loop.run_in_executor(self.replan_pool, rt.warm_up_replan, self.cfg)
        # Start the helper threads now: no thread start during a flight.
        await self.loop.run_in_executor(self.io_pool, int, 0)
        await self.loop.run_in_executor(self.decode_pool, warm_validators)
        await asyncio.gather(*(self.loop.run_in_executor(self.brake_pool, rt.warm_up_brake, self.cfg)
                               for _ in range(2)))
        self.gc.start(time.monotonic())
        self._sender_failure = self.loop.create_future()
        self.sender.start(rtsched.starter())
        log.info("setpoint thread: %.0f Hz, %s scheduling", self.cfg.setpoints.rate_hz, self.sender.scheduling)
        loops = [self.heartbeat_loop(), self.telemetry_loop(), self.status_loop(),
                 self.inbox_loop(), self.ordered_loop()]
        runners = [asyncio.create_task(c) for c in loops]
        runners.append(asyncio.ensure_future(self._sender_failure))
        self.notifier.ready(f"vehicle {self.cfg.vehicle.id}: zenoh and mavlink up")
        self.event("started", f"companion for {self.cfg.vehicle.id} started", mavlink=self.cfg.mavlink.url)
        try:
            stopper = asyncio.create_task(self.stop.wait())
            done, _ = await asyncio.wait([stopper, *runners], return_when=asyncio.FIRST_COMPLETED)
            for t in done:
                if t is not stopper and t.exception() is not None:
                    raise t.exception()  # type: ignore[misc]
        finally:
            self.notifier.stopping()
            self.streaming = False
            self.sender.stop()
            for t in [*runners, *self.tasks, *([self.task] if self.task else [])]:
                t.cancel()
            await asyncio.gather(*runners, *self.tasks, return_exceptions=True)
            with contextlib.suppress(Exception):
                self.event("stopped", "companion stopping")
            self.link.close()
            self.zio.close()
            self.pool.shutdown(wait=False, cancel_futures=True)
            self.urgent_pool.shutdown(wait=False, cancel_futures=True)
            self.io_pool.shutdown(wait=False, cancel_futures=True)
            self.replan_pool.shutdown(wait=False, cancel_futures=True)
            self.decode_pool.shutdown(wait=False, cancel_futures=True)
            self.brake_pool.shutdown(wait=False, cancel_futures=True)
            self.gc.stop()
            restore_logging(self._log_listener)


def rt_add_obstacles(new: list[Polytope]) -> Any:
    return AddObstacles(tuple(new))


def period_stats(periods: collections.deque[float]) -> dict[str, float] | None:
    """p50/p99/max of the last setpoint periods (ms), measured at the send."""
    if len(periods) < 2:
        return None
    p = np.asarray(periods) * 1000.0
    return {"p50": round(float(np.percentile(p, 50)), 3), "p99": round(float(np.percentile(p, 99)), 3),
            "max": round(float(p.max()), 3), "n": len(p)}


def log_off_loop() -> logging.handlers.QueueListener | None:
    """Route the root logger's handlers through a queue served by a listener thread: a log call
    on the loop then only formats and enqueues, it never waits on a write."""
    root = logging.getLogger()
    handlers = [h for h in root.handlers if not isinstance(h, logging.handlers.QueueHandler)]
    if not handlers:
        return None
    q: queue.SimpleQueue[logging.LogRecord] = queue.SimpleQueue()
    listener = logging.handlers.QueueListener(q, *handlers, respect_handler_level=True)
    for h in handlers:
        root.removeHandler(h)
    root.addHandler(logging.handlers.QueueHandler(q))
    listener.start()
    return listener


def restore_logging(listener: logging.handlers.QueueListener | None) -> None:
    if listener is None:
        return
    root = logging.getLogger()
    for qh in [h for h in root.handlers if isinstance(h, logging.handlers.QueueHandler)]:
        root.removeHandler(qh)
    listener.stop()  # writes out what is still queued
    for h in listener.handlers:
        root.addHandler(h)


# Nice increments (relative to the service's own, e.g. systemd's Nice=-5) of the planner
# processes: mission planning yields the CPU to the service's process on a busy computer;
# the urgent worker (replans, the fallback after a failed local replan) less so, as it races a
# braking deadline, but still behind the loop.
PLANNER_NICE = 10
URGENT_NICE = 3


def background_priority(increment: int) -> None:
    with contextlib.suppress(OSError):
        os.nice(increment)


def make_planner_pool(cfg: Config, workers: int | None = None, nice: int = PLANNER_NICE) -> Executor:
    n = cfg.planner.workers if workers is None else workers
    if cfg.planner.executor == "process":
        return ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=background_priority, initargs=(nice,))
    # Threads keep normal priority: a low-priority thread holding the GIL would hold it longer.
    return ThreadPoolExecutor(n, thread_name_prefix="planner")


async def run(config: Config, *, stop: asyncio.Event | None = None) -> None:
    """Run the service until `stop` is set (or forever)."""
    await Service(config, stop).run()
