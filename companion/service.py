"""The companion service: wiring only. One asyncio loop per vehicle.

Zenoh in (mission, obstacles, change, command) -> `wire.messages.read` (typed, NED) -> one
handler per kind -> planning in workers -> a verified trajectory swapped in by `Control` ->
the setpoint thread -> MAVLink out. Telemetry comes back over MAVLink and goes out on Zenoh.

The parts, each the one owner of what it holds:
- `Supervisor` (supervisor.py): the state and every flag about the vehicle's situation
  (flight.py), changed only by the events the other parts submit to it;
- `Control` (control.py): what is flown: the mission's route, the trajectory the setpoint
  thread flies and its time base, changed together; what is left of a mission (loaded,
  interrupted);
- `Navigator` (navigator.py): planning missions, changes and pop-ups in flight; the obstacles;
- `Commands` (commands.py): the command sequences; `HandOver` (handover.py): leaving the
  vehicle to the autopilot; `Tracking` (tracking.py): the tracking error and the lead;
  `AutopilotWatch` (autopilot.py): reports;
- `Runtime` (runtime.py): executors; `Reporter` (report.py): events.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import sys
import time
from typing import Any

import numpy as np

from companion import rtsched
from companion.autopilot import AutopilotWatch
from companion.braking import warm_up_brake
from companion.commands import Commands
from companion.config import Config
from companion.control import Control
from companion.deconfliction import REPUBLISH, Deconfliction
from companion.fleet import FleetFrame
from companion.handover import HandOver
from companion.limits_watch import LimitsWatch
from companion.mission import warm_up, warm_up_replan
from companion.navigator import Navigator
from companion.recorder import tap_for
from companion.report import Reporter
from companion.runtime import GcPacer, Runtime, log_off_loop, restore_logging, return_heap
from companion.sdnotify import Notifier
from companion.sendproc import SetpointProcess
from companion.setpoints import (
    DeadlineScheduler,
    Liveness,
    SetpointSender,
    Tick,
    YawPolicy,
    sleep_until,
)
from companion.supervisor import Supervisor
from companion.tracking import Tracking
from companion.wire import encode as enc
from companion.wire.errors import InternalError, MessageError, Oversized, quote
from companion.wire.mavlink import MavlinkLink
from companion.wire.messages import (
    Change,
    Command,
    Message,
    MissionSpec,
    ObstacleUpdate,
    fence_at_home,
    read,
    warm_validators,
)
from companion.wire.zenoh import ZenohIO
from planner_core import FloatArray, Trajectory, hold

log = logging.getLogger("companion")

INLINE_DECODE_BYTES = 4096
# s: setpoints withheld after a stall for less than this (half PX4's default COM_OF_LOSS_T):
# the autopilot still flies our plan, so the companion keeps control and holds
STALL_HOLD_WITHIN = 0.5


class Service:
    def __init__(self, cfg: Config, stop: asyncio.Event | None = None,
                 abandon: asyncio.Event | None = None) -> None:
        self.cfg = cfg
        # `requested`: asked to stop (first SIGINT/SIGTERM): hand over, then stop; `abandon`
        # (a second signal): give up the hand-over at once; `stop`: the loops end.
        self.requested = stop or asyncio.Event()
        self.abandon = abandon or asyncio.Event()
        self.stop = asyncio.Event()
        self.flight = Supervisor()
        self.report = Reporter(self.flight, self._publish)
        self.runtime = Runtime(cfg, on_planner_died=lambda: self.report.event(
            "error", "the planner process died; restarted it (this request failed)"))
        self.link = MavlinkLink(cfg)
        self.tap = self.runtime.tap = self.link.tap = tap_for(cfg)  # recorder and live view (issue 23)
        self.yaw = YawPolicy(cfg.setpoints.yaw_mode, cfg.setpoints.yaw, cfg.setpoints.yaw_min_speed)
        self.sender: SetpointSender | SetpointProcess
        if cfg.setpoints.process:
            self.sender = SetpointProcess(cfg.setpoints.rate_hz, self.link.transport, self.yaw,
                                          self._tick_from_thread, self._sender_failed,
                                          priority=cfg.setpoints.realtime_priority)
        else:
            self.sender = SetpointSender(cfg.setpoints.rate_hz, self.link.send_setpoint, self.yaw,
                                         self._tick_from_thread, self._sender_failed,
                                         priority=cfg.setpoints.realtime_priority)
        self.control = Control(self.sender, self.link.send_setpoint, self.yaw, cfg.setpoints.rate_hz,
                               on_new_plan=self.publish_trajectory, on_latency=self._latency_event)
        self.navigator = Navigator(cfg, self.flight, self.control, self.runtime, self.report, self._position)
        self.commands = Commands(cfg, self.flight, self.control, self.link, self.navigator, self.report, self.runtime)
        self.tracking = Tracking(cfg, self.flight, self.control, self.link, self.navigator, self.report)
        self.handover = HandOver(cfg, self.flight, self.control, self.link, self.navigator, self.report,
                                 self.commands.cancel_sequence)
        self.liveness = Liveness(cfg.setpoints.loop_stall_limit)
        self.sender.liveness = self.liveness
        # what the supervisor decides to stop is stopped here: the stream, and any command sequence
        self.flight.connect(release=self.commands.release_control, stop_stream=self.control.release)
        self.watch = AutopilotWatch(cfg, self.flight, self.link, self.report,
                                    on_position=self.tracking.check_tracking, stalled=self._stalled)
        self.link.on_message = self._on_mavlink
        # where the autopilot's local frame sits in the fleet frame ([fleet] origin; companion.fleet)
        self.fleet = FleetFrame(cfg.fleet)
        # the other vehicles' trajectories and the commit protocol ([fleet] separation; companion.deconfliction)
        self.deconfliction = Deconfliction(cfg, self.fleet, lambda: self.control.t_base, self._publish_proposal,
                                           self.report.event)
        self.navigator.fleet = self.deconfliction
        self.deconfliction.on_replan = self.navigator.fleet_replan
        self.deconfliction.on_clock_off = self.navigator.fleet_stop
        # the autopilot's own limits: read at link-up and after a reconnect, planned within
        self.limits = LimitsWatch(cfg, self.link, self.report)
        self.commands.events_heard = self.watch.events_heard  # the arming-check report, for refusals
        self.watch.on_link_up = self._link_up
        self.navigator.limits = self.limits
        self.link.on_ignored = self._mavlink_ignored
        # lag compensation: a fixed lead, or "auto" (set by Tracking from its estimate)
        self.tracking.steer_lead(self.sender)
        self.zio: ZenohIO | None = None
        self.notifier = Notifier()
        self.gc = GcPacer()
        self.loop: asyncio.AbstractEventLoop | None = None
        self.tracking_error: float | None = None
        self.tasks: list[asyncio.Task[Any]] = []
        self._traj_seq = 0
        self._traj_published = 0
        self._traj_bytes: bytes | None = None
        self._sender_failure: asyncio.Future[None] | None = None
        self._ordered: asyncio.Queue[tuple[str, bytes | Oversized, float]] = asyncio.Queue()
        self._missions: list[asyncio.Task[Any]] = []  # mission handlers not yet done
        self._drops = 0
        self._drop_said = -math.inf
        self._wrong_said: dict[str, float] = {}  # key expression -> when its refusal was said
        self.setpoints_stalled = False
        self._ticked = asyncio.Event()
        self._log_listener: Any = None
        self._handed_over = False  # the last run's hand-over (said in the `stopped` event)
        self._runners: list[asyncio.Future[Any]] = []  # the running tasks, cancelled at the end
        self._heap_return: asyncio.TimerHandle | None = None

    def _position(self) -> FloatArray:
        return self.link.state.position

    def _publish(self, key: str, body: dict[str, Any]) -> None:
        if self.zio is not None:
            # which companion said it: clients check it against the session that answers
            # their status query (companion.__main__, `send`/`watch`)
            self.zio.publish(key, {**body, "session": self.zio.zid})
        if key == "events" and (body.get("type") == "mission_complete" or (
                body.get("type") in ("accepted", "rejected") and body.get("key") in ("mission", "change"))):
            self._return_heap_soon()

    def _return_heap_soon(self) -> None:
        """After a mission or change was taken, refused or finished, what planning it allocated
        is garbage; glibc keeps the freed pages for reuse (the main process grew 121 -> 222 MB
        over a campaign of big missions, issue 21), so hand them back, once things settle."""
        loop = self.loop
        if loop is None or self._heap_return is not None:
            return

        def run() -> None:
            self._heap_return = None
            loop.run_in_executor(self.runtime.io_pool, return_heap)

        self._heap_return = loop.call_later(2.0, run)

    def _latency_event(self, what: str, seconds: float, immediate: bool, sent_mono: float) -> None:
        # sent_mono: CLOCK_MONOTONIC at the send (shared by every process on this machine), so a
        # benchmark can find this setpoint in a capture and leave it out of period statistics.
        self.report.event("latency", f"{what}: first setpoint of the new plan {seconds * 1000:.1f} ms after the message",
                          what=what, latency_ms=round(seconds * 1000, 2), immediate=immediate,
                          sent_mono=round(sent_mono, 6))

    # -- the plan, published ---------------------------------------------------------------

    def publish_trajectory(self, traj: Trajectory) -> None:
        """Encode off the loop (json.dumps of a long plan holds the GIL), then publish."""
        if self.zio is None or self.loop is None:
            return
        self._traj_seq += 1
        seq = self._traj_seq
        self.tap.flown(traj, self.control.t_base, time.monotonic())
        fleet = self.deconfliction.committed_section(traj)
        fut = self.loop.run_in_executor(self.runtime.io_pool, enc.encode_trajectory, traj, fleet)

        def done(f: asyncio.Future[bytes]) -> None:
            if f.cancelled() or f.exception() is not None or seq < self._traj_published:
                return
            self._traj_published = seq
            self._traj_bytes = f.result()
            if self.zio is not None:
                self.zio.publish_bytes("trajectory", self._traj_bytes)

        fut.add_done_callback(done)

    def _publish_proposal(self, payload: bytes) -> None:
        if self.zio is not None:
            self.zio.publish_bytes("trajectory", payload)

    async def fleet_loop(self) -> None:
        """Our committed trajectory again every REPUBLISH s: a vehicle that joins late, or lost a
        put, learns what we fly (only with [fleet] separation)."""
        while not self.stop.is_set():
            await asyncio.sleep(REPUBLISH)
            await self.after_tick()
            if self.zio is not None and self._traj_bytes is not None and self.control.active is not None:
                self.zio.publish_bytes("trajectory", self._traj_bytes)

    def query_plan(self) -> bytes | None:
        return None if self.control.active is None else self._traj_bytes

    def query_status(self) -> bytes | None:
        return enc.encode(self.status())

    # -- the setpoint thread's ticks --------------------------------------------------------------

    def _tick_from_thread(self, tick: Tick) -> None:
        """Called by the setpoint thread after each tick: the rest happens on the loop."""
        if tick.setpoint is not None and tick.error is None and isinstance(self.sender, SetpointProcess):
            # the process wrote it: the recorder gets it from its record (the thread's own sends
            # reach the recorder through pymavlink's send callback)
            self.tap.mavlink_sent(self.link.setpoint_message(tick.setpoint, tick.now), tick.now)
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
                what = "process" if isinstance(self.sender, SetpointProcess) else "thread"
                fut.set_exception(RuntimeError(f"the setpoint {what} failed: {exc!r}"))

        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(fail)

    def _on_tick(self, tick: Tick) -> None:
        """Bookkeeping of one setpoint tick, on the loop, right after the send."""
        # Both the thread and the loop must be alive for systemd's watchdog to be fed.
        self.notifier.watchdog()
        if tick.error is not None:
            log.warning("setpoint not sent: %s", tick.error)
        t = self.control.on_tick(tick)
        if t is not None:
            self.navigator.progress(t)
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

    async def after_tick(self) -> None:
        """Wait for the moment right after the next setpoint tick, when the next deadline is
        furthest away: periodic publishing done then cannot make a setpoint late."""
        await self._ticked.wait()

    # -- periodic loops -------------------------------------------------------------------------

    async def heartbeat_loop(self) -> None:
        sched = DeadlineScheduler(time.monotonic(), self.cfg.mavlink.heartbeat_hz)
        while not self.stop.is_set():
            with contextlib.suppress(OSError):
                self.link.send_heartbeat()
            self.watch.check_link()
            await sleep_until(sched.next_deadline(time.monotonic()), spin=0.0)

    async def telemetry_loop(self) -> None:
        sched = DeadlineScheduler(time.monotonic(), 20.0)
        while not self.stop.is_set():
            await sleep_until(sched.next_deadline(time.monotonic()), spin=0.0)
            await self.after_tick()
            st = self.link.state
            if st.has_position and self.zio is not None:
                self.zio.publish("telemetry", enc.telemetry(st.position, st.velocity, st.attitude, st.armed, st.mode))
            self.watch.check_link()

    async def status_loop(self) -> None:
        last = 0.0
        while not self.stop.is_set():
            await asyncio.sleep(0.05)
            await self.after_tick()
            now = time.monotonic()
            if self.report.dirty or now - last >= 0.5:
                self.report.dirty = False
                last = now
                if self.zio is not None:
                    self.zio.publish("status", self.status())

    def _on_mavlink(self, kind: str, msg: Any) -> None:
        self.watch.on_message(kind, msg)
        if kind in ("GPS_GLOBAL_ORIGIN", "HOME_POSITION") and self.fleet.enabled:
            st = self.link.state
            said = self.fleet.update(st.gps_origin, st.home_lla, st.home)
            if said is not None:
                self.report.event("fleet_frame", said, **(self.fleet.status() or {}))

    def status(self) -> dict[str, Any]:
        st, ctl = self.link.state, self.control
        # measured position against the setpoint of the measurement's own time (Tracking)
        self.tracking_error = self.tracking.tracking_error if ctl.streaming else None
        return {
            "vehicle": self.cfg.vehicle.id,
            "session": self.zio.zid if self.zio is not None else None,
            "time": round(time.time(), 3),
            "state": self.flight.state.value,
            "airborne": self.flight.airborne,
            "autopilot": st.autopilot,
            "mode": st.mode,
            # a disarmed PX4 reports its last user mode (OFFBOARD after an offboard landing):
            # that flies nothing
            "active_mode": st.mode if st.armed else None,
            "armed": st.armed,
            "origin": "local",
            "home": enc.vec(st.home) if st.home is not None else None,
            # a usable LOCAL_POSITION_NED: real ArduCopter reports home ~22 s before its first one
            "position_ok": st.position_problem() is None,
            "geofence": self._geofence(),
            "ground_z": enc.num(self.flight.ground_z),
            "link": self.link.link_ok() if self.flight.seen_link else False,
            "streaming": ctl.streaming,
            **self.navigator.status_fields(),
            "tracking_error": enc.num(self.tracking_error),
            "tracking_error_max": enc.num(self.tracking.tracking_error_max),
            "lead_ms": round(self.sender.lead * 1000, 1),
            "lag_estimate_ms": enc.ms(self.tracking.lag_estimate),
            "tracking_allowance": self.cfg.planner.tracking_allowance,
            **self._limits_status(),
            "message_to_setpoint_ms": enc.ms(ctl.setpoint_latency),
            "setpoints_sent": self.link.sent_setpoints,
            "setpoint_gap_max_ms": round(ctl.setpoint_gap_max * 1000, 2),
            "setpoint_period_ms": ctl.period_stats(),
            "gc_pause_max_ms": round(self.gc.worst * 1000, 2),
            "setpoints_stalled": self.setpoints_stalled,
            **self.tap.status_fields(),
            "mavlink_ignored": dict(self.link.gate.ignored) if self.link.gate is not None else {},
            "fleet": self._fleet_status(),
        }

    def _fleet_status(self) -> dict[str, Any] | None:
        st = self.fleet.status()
        sep = self.deconfliction.status()
        return st if st is None or sep is None else {**st, "deconfliction": sep}

    def _limits_status(self) -> dict[str, Any]:
        """The autopilot's limits (each with its source) and the bounds flown because of them."""
        lim = self.limits.assumed()
        b = self.limits.default_bounds()
        return {
            "autopilot_limits": None if lim is None else {
                **lim.as_status(), "read": self.limits.limits is not None, "headroom": self.limits.headroom},
            "bounds_flown": {name: {"lo": [round(float(x), 4) for x in b.lo[i]],
                                    "hi": [round(float(x), 4) for x in b.hi[i]],
                                    "horizontal": enc.num(float(b.horizontal[i]))}
                             for i, name in enumerate(("velocity", "acceleration", "jerk", "snap"))},
        }

    def _geofence(self) -> dict[str, Any]:
        """The geofence box in use, in the local frame, and what it is relative to."""
        home = self.link.state.home
        fence = fence_at_home(self.cfg, home).geofence
        follows = self.cfg.geofence.origin == "home" and home is not None
        return {"min": enc.vec(np.asarray(fence.min)), "max": enc.vec(np.asarray(fence.max)),
                "relative_to": "home" if follows else "local"}

    # -- inbound messages: one reader per kind ------------------------------------------------------

    async def inbox_loop(self) -> None:
        """Small obstacle messages (pop-ups) are handled at once; the rest keep their order in
        `ordered_loop`, where one large mission may take a while to validate: a pop-up must not
        wait behind it. (Obstacle updates do not depend on a mission being loaded first: a
        mission is planned against the obstacles known when it is planned.) Nothing a message
        does ends this loop: the last-resort guard turns it into a rejection and an error."""
        assert self.zio is not None
        self.zio.on_dropped = self._dropped
        while not self.stop.is_set():
            kind, payload, arrived = await self.zio.inbox.get()
            try:
                self.tap.inbound(kind, payload, arrived)
                if kind == "obstacles" and len(payload) <= INLINE_DECODE_BYTES:
                    self._dispatch(kind, payload, arrived, read(kind, payload, self.cfg, self.link.state.home,
                                                                fleet=self.fleet.for_messages()))
                elif self._ordered.qsize() >= self.cfg.limits.max_queued_messages:
                    self._dropped(kind, len(payload))
                else:
                    self._ordered.put_nowait((kind, payload, arrived))
            except Exception as exc:
                self._unforeseen(kind, payload, exc)
            # one message per loop step: a backlog of small messages decoded here must not
            # hold up the timers (periodic status, stall checks) behind it
            await asyncio.sleep(0)

    async def ordered_loop(self) -> None:
        while not self.stop.is_set():
            kind, payload, arrived = await self._ordered.get()
            # JSON Schema validation is pure Python (~0.1 ms per waypoint): large messages off
            # the loop, small ones (a command: well under a millisecond) right here, which
            # spares two thread hand-offs. One message at a time, so the order is kept.
            try:
                assert self.loop is not None
                job = functools.partial(read, kind, payload, self.cfg, self.link.state.home,
                                        home_pending=self.link.state.home_pending,
                                        fleet=self.fleet.for_messages())
                msg = job() if len(payload) <= INLINE_DECODE_BYTES else \
                    await self.loop.run_in_executor(self.runtime.decode_pool, job)
                self._dispatch(kind, payload, arrived, msg)
            except Exception as exc:
                self._unforeseen(kind, payload, exc)

    def _unforeseen(self, kind: str, payload: bytes | Oversized, exc: BaseException) -> None:
        """The last resort at the loop boundary: a rejection and an error event, never an exit."""
        log.error("message on %s: unforeseen %r", kind, exc, exc_info=exc)
        what = f"{type(exc).__name__}: {quote(str(exc))}"
        with contextlib.suppress(Exception):
            self.report.reject(kind, "", f"internal error while handling the message: {what}", bytes=len(payload))
            self.report.event("error", f"{kind}: internal error while handling a message: {what}; "
                              "holding the current plan", key=kind)

    def _dropped(self, kind: str, size: int) -> None:
        """A message refused because the inbound queues are full: said at most once a second."""
        self._drops += 1
        now = time.monotonic()
        if now - self._drop_said >= 1.0:
            n, self._drops, self._drop_said = self._drops, 0, now
            lim = self.cfg.limits.max_queued_messages
            self.report.reject(kind, "", f"{n} message(s) dropped: {lim} messages are already queued "
                               f"([limits] max_queued_messages = {lim})", bytes=size, dropped=n)

    def _refused(self, counts: dict[str, int]) -> None:
        """Messages refused on arrival over `[limits] inbound_rate`: one event for all of them."""
        lim = self.cfg.limits
        total = sum(counts.values())
        each = ", ".join(f"{n} on {k}" for k, n in sorted(counts.items()))
        self.report.reject(next(iter(sorted(counts))) if len(counts) == 1 else "", "",
                           f"{total} message(s) refused on arrival ({each}): more than {lim.inbound_burst:g} at once "
                           f"or {lim.inbound_rate:g} a second per key ([limits] inbound_rate, inbound_burst)",
                           refused=counts)

    def _mavlink_ignored(self, counts: dict[str, int], rebound: str | None) -> None:
        """MAVLink messages not from the bound autopilot (never acted on), or a re-bind."""
        gate = self.link.gate
        if rebound is not None:
            self.report.event("mavlink_peer", f"the autopilot's address changed ({rebound}) after its old address "
                              f"was silent for over {self.cfg.mavlink.link_timeout:g} s ([mavlink] link_timeout): "
                              "re-bound to it", rebound=rebound)
            return
        words = {"other_address": "from another address than the autopilot's",
                 "other_id": "from another system or component id",
                 "unsigned": "unsigned or not signed with our key ([mavlink] require_signed_inbound)",
                 "before_binding": "before the autopilot's first heartbeat"}
        where = f" (bound to {gate.address[0]}:{gate.address[1]})" if gate is not None and gate.address else ""
        text = "; ".join(f"{n} {words.get(why, why)}" for why, n in counts.items())
        self.report.event("mavlink_ignored", f"MAVLink messages ignored, not from the autopilot "
                          f"{self.cfg.vehicle.sysid}/{self.cfg.vehicle.autopilot_component}{where}: {text}",
                          ignored=counts, total=dict(gate.ignored) if gate is not None else None)

    def _wrong_key(self, kind: str, key: str, size: int) -> None:
        """A put on a key expression other than this vehicle's exact key: never acted on. One
        event per key expression a second (a put on `bezier/drone1/*` reaches all four kinds)."""
        now = time.monotonic()
        if now - self._wrong_said.get(key, -math.inf) < 1.0:
            return
        if len(self._wrong_said) > 64:  # bounded: a peer may try many expressions
            self._wrong_said = {k: t for k, t in self._wrong_said.items() if now - t < 1.0}
        self._wrong_said[key] = now
        self.report.reject(kind, "key_expr", f"a put on key expression {quote(key, 80)} is refused: only this "
                           f"vehicle's exact keys ({self.cfg.key('<kind>')}) are acted on, never a wildcard or a "
                           "key matching several vehicles or kinds (send one put per vehicle)",
                           key_expr=key[:100], bytes=size)

    def _dispatch(self, kind: str, payload: bytes | Oversized, arrived: float, msg: Message | MessageError) -> None:
        if isinstance(msg, MessageError):
            self.report.reject(kind, msg.field, msg.reason, bytes=len(payload))
            if isinstance(msg, InternalError):
                self.report.event("error", f"{kind}: {msg.reason}; holding the current plan", key=kind)
            return
        handler: Any
        if isinstance(msg, MissionSpec):
            self._missions = [t for t in self._missions if not t.done()]
            lim = self.cfg.limits.max_pending_missions
            if len(self._missions) >= lim:
                self.report.reject(kind, "", f"mission {msg.id}: {len(self._missions)} missions are already being "
                                   f"checked or planned ([limits] max_pending_missions = {lim})", mission=msg.id)
                return
            handler = self.navigator.on_mission
        elif isinstance(msg, ObstacleUpdate):
            handler = self.navigator.on_obstacles
        elif isinstance(msg, Change):
            handler = self.navigator.on_change
        elif isinstance(msg, Command):
            handler = self.commands.on_command
        else:  # pragma: no cover - read() makes only these
            raise TypeError(f"no handler for {type(msg).__name__}")
        task = asyncio.create_task(self._guard(kind, handler(msg, arrived)))
        if isinstance(msg, MissionSpec):
            self._missions.append(task)
        self.tasks.append(task)
        self.tasks = [t for t in self.tasks if not t.done()]

    # -- the setpoint-stream watchdog ---------------------------------------------------------------

    async def setpoint_watchdog(self) -> None:
        """Notices when setpoints stop leaving while streaming (the setpoint thread stalled or
        its sends fail), and when this loop itself was held up: status (`setpoints_stalled`) and
        an `error` event say so, and `setpoints_resumed` when they flow again. (A hung loop is
        systemd's watchdog's: it is fed only from setpoint ticks handled on the loop.)"""
        period = 1.0 / self.cfg.setpoints.rate_hz
        limit = max(0.1, 5 * period)
        count, since = self.link.sent_setpoints, time.monotonic()
        expected = since + period
        while not self.stop.is_set():
            await asyncio.sleep(period)
            now = time.monotonic()
            if now - expected > 0.25:
                self.report.event("error", f"the event loop was held up for {(now - expected) * 1000:.0f} ms",
                                  loop_stall_ms=round((now - expected) * 1000, 1))
            expected = now + period
            n = self.link.sent_setpoints
            if n != count or not self.control.streaming:
                if self.setpoints_stalled:
                    self.setpoints_stalled = False
                    self.report.event("setpoints_resumed", f"setpoints leave again after {(now - since) * 1000:.0f} ms",
                                      silence_ms=round((now - since) * 1000, 1))
                count, since = n, now
            elif not self.setpoints_stalled and now - since > limit:
                self.setpoints_stalled = True
                self.report.event("error", f"setpoints stopped leaving: none sent for {(now - since) * 1000:.0f} ms "
                                  "while streaming", silence_ms=round((now - since) * 1000, 1))

    # -- the companion's own liveness ------------------------------------------------------------

    def _link_up(self, why: str) -> None:
        """The autopilot found (link-up, reconnect): its limits read, the lead it starts with."""
        self.limits.read(why)
        self.tracking.autopilot_found()

    def _stalled(self) -> bool:
        """The companion is stalled or just woke from a stall (see setpoints.Liveness); not
        before the setpoint thread runs (the warm-up does not beat)."""
        if self.sender.native_id is None:
            return False
        return self.liveness.stale() or self.sender.withheld

    async def loop_liveness(self) -> None:
        """Beats every setpoint period, so the setpoint thread knows the loop runs. When this
        loop did not run for `[setpoints] loop_stall_limit`, or the setpoint thread withheld
        setpoints (it saw the loop, or itself, stall): say that the companion - not the link -
        caused the episode, and deal with it before setpoints leave again. Setpoints silent for
        under STALL_HOLD_WITHIN: the autopilot still flies our plan; stop the mission and hold
        (it waits for `resume`). Longer: the autopilot may have left OFFBOARD on its own;
        release control (FAILSAFE; the autopilot is asked to hold) and wait for `start`."""
        period = 1.0 / self.cfg.setpoints.rate_hz
        limit = self.cfg.setpoints.loop_stall_limit
        live = self.liveness
        live.beat()
        was = self.flight.state
        while not self.stop.is_set():
            await asyncio.sleep(period)
            gap = live.beat()
            withheld = live.withheld
            if gap <= limit and withheld is None:
                was = self.flight.state  # as it was before any stall
                continue
            now = time.monotonic()
            what = "the setpoint thread" if withheld is not None and withheld[1] == "thread" else "its event loop"
            stall = max(gap, withheld[2] if withheld is not None else 0.0)
            silence = now - live.last_sent
            reason = f"the companion stalled ({what} did not run for {stall * 1000:.0f} ms)"
            if not self.flight.controlling:
                reaction = "not in control"
            elif withheld is not None and silence >= STALL_HOLD_WITHIN:
                self.handover.after_stall(reason)
                reaction = "released control"
            else:
                reaction = self.handover.hold_after_stall(reason)
            live.release()
            link = self.link.link_ok()
            silent = (f"setpoints were withheld for {silence * 1000:.0f} ms" if withheld is not None
                      else "no setpoint was withheld")
            self.report.event(
                "stalled", f"{reason} while {was.value}: cause the companion, not the link (the autopilot "
                f"{'is heard' if link else 'is not heard either'}); {silent}; {reaction}; now "
                f"{self.flight.state.value}, mode {self.link.state.mode}",
                cause="companion", stalled=what.removeprefix("its ").replace(" ", "_"), stall_ms=round(stall * 1000, 1),
                setpoints_withheld=withheld is not None,
                silence_ms=enc.ms(silence, 1) if withheld is not None else None,
                previous_state=was.value, link=link, mode=self.link.state.mode)
            was = self.flight.state

    async def _guard(self, kind: str, coro: Any) -> None:
        try:
            await coro
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # a bug in one handler must not stop the service
            log.exception("handler for %s failed", kind)
            self.report.event("error", f"{kind}: internal error: {exc!r}; holding the current plan", key=kind)

    # -- run ----------------------------------------------------------------------------------------

    async def _warm_up(self) -> None:
        """First calls pay for imports and caches; pay them now, not during a flight. Also
        starts every helper thread now: no thread start during a flight."""
        rt, loop = self.runtime, self.loop
        assert loop is not None
        await asyncio.gather(rt.plan(warm_up, self.cfg), rt.plan(warm_up, self.cfg, urgent=True))
        # a second, warm plan: the first estimate of planning time in this service (in-flight splits)
        t0 = time.monotonic()
        await rt.plan(warm_up, self.cfg)
        self.navigator._measured(time.monotonic() - t0, 2)
        await loop.run_in_executor(rt.io_pool, enc.encode_trajectory, hold(np.zeros(3), 0.0))
        await loop.run_in_executor(rt.replan_pool, warm_up_replan, self.cfg)
        await loop.run_in_executor(rt.decode_pool, warm_validators)
        await asyncio.gather(*(loop.run_in_executor(rt.brake_pool, warm_up_brake, self.cfg) for _ in range(2)))

    async def run(self) -> bool:
        """Run until asked to stop; returns True when the vehicle was handed over (or there
        was nothing to hand over); raises what failed inside, after the hand-over.

        Four phases: set up (logging, Zenoh, the recorder, MAVLink, the warm-up), start (paced
        GC, the setpoint sender, the tasks), run (until a stop is asked or a task fails), stop
        (hand the vehicle over). Each step that takes a resource registers its undoing as it
        takes it, and they are undone in reverse, whichever phase failed: a failed warm-up
        leaves no socket, session, thread or pool behind (issue 22.5)."""
        self.loop = asyncio.get_running_loop()
        self.runtime.loop = self.loop
        self._handed_over = False
        failure: BaseException | None = None
        async with contextlib.AsyncExitStack() as undo:
            await self._set_up(undo)
            runners, inbound, sender = self._start(undo)
            try:
                stopper: asyncio.Future[Any] = asyncio.create_task(self.requested.wait())
                done, _ = await asyncio.wait([stopper, *runners], return_when=asyncio.FIRST_COMPLETED)
                stopper.cancel()
                for t in done:
                    if t is not stopper and not t.cancelled() and t.exception() is not None:
                        failure = t.exception()
                self.notifier.stopping()
                # No new message is taken from now on; what was being handled is cancelled.
                for t in [*inbound, *self.tasks]:
                    t.cancel()
                await asyncio.gather(*inbound, *self.tasks, return_exceptions=True)
                why = "stop requested" if failure is None else f"internal failure ({failure})"
                if failure is not None:
                    log.critical("%s: handing the vehicle over to the autopilot", why)
                self._handed_over = await self._hand_over(why, can_brake=failure is None or sender not in done)
            finally:
                self.notifier.stopping()
                self.stop.set()
        if failure is not None:
            raise failure
        return self._handed_over

    async def _set_up(self, undo: contextlib.AsyncExitStack) -> None:
        """Logging off the loop, Zenoh, the recorder, the MAVLink link, the warm-up; each undone in reverse."""
        assert self.loop is not None
        # Log output (a file or journald on a busy disk) is written by a thread of its own.
        self._log_listener = log_off_loop()
        undo.callback(restore_logging, self._log_listener)
        undo.callback(self.gc.stop)  # a no-op until it starts
        undo.callback(self.runtime.shutdown)
        # The loop and the helper threads hold the GIL in pure-Python stretches; a short
        # switch interval bounds how long the setpoint thread can wait for it.
        sys.setswitchinterval(0.0005)
        self.zio = ZenohIO(self.cfg, self.loop)
        self.zio.on_refused = self._refused
        self.zio.tap = self.tap
        undo.callback(self.tap.close)
        self.tap.open()
        self.zio.on_wrong_key = self._wrong_key
        undo.callback(self.zio.close)
        self.zio.open({"plan": self.query_plan, "status": self.query_status})
        if self.deconfliction.enabled:
            self.zio.watch_fleet(self.deconfliction.on_trajectory, self.deconfliction.on_alive)
        undo.callback(self.link.close)
        self.link.open(self.loop)
        undo.callback(self._report_stopped)  # said while Zenoh is still open
        self._runners = []
        undo.push_async_callback(self._cancel)  # after the sender stopped (below: undone first)
        await self._warm_up()

    def _start(self, undo: contextlib.AsyncExitStack) -> tuple[list[asyncio.Future[Any]], list[asyncio.Task[Any]],
                                                               asyncio.Future[Any]]:
        """Paced GC, the setpoint sender, the periodic and inbound tasks; returns (every runner,
        the inbound tasks, the sender's failure future)."""
        assert self.loop is not None
        self.gc.start(time.monotonic())
        self._sender_failure = self.loop.create_future()
        self.liveness.beat()  # the warm-up above is not a stall
        undo.callback(self.sender.stop)
        self.sender.start(rtsched.starter())
        undo.callback(self.control.release)  # nothing is streamed once the sender stops
        if isinstance(self.sender, SetpointProcess):
            self.link.use_writer(self.sender)
        log.info("setpoint %s: %.0f Hz, %s scheduling", "process" if self.cfg.setpoints.process else "thread",
                 self.cfg.setpoints.rate_hz, self.sender.scheduling)
        periodic = [asyncio.create_task(c) for c in (self.heartbeat_loop(), self.telemetry_loop(), self.status_loop(),
                                                       self.setpoint_watchdog(), self.loop_liveness())]
        if self.deconfliction.enabled:
            periodic.append(asyncio.create_task(self.fleet_loop()))
        inbound = [asyncio.create_task(c) for c in (self.inbox_loop(), self.ordered_loop())]
        sender = asyncio.ensure_future(self._sender_failure)
        runners: list[asyncio.Future[Any]] = [*periodic, *inbound, sender]
        self._runners = runners
        self.notifier.ready(f"vehicle {self.cfg.vehicle.id}: zenoh and mavlink up")
        self.report.event("started", f"companion for {self.cfg.vehicle.id} started", mavlink=self.cfg.mavlink.url)
        return runners, inbound, sender

    async def _cancel(self) -> None:
        seq = self.commands.task
        runners = self._runners
        for t in [*runners, *self.tasks, *([seq] if seq else [])]:
            t.cancel()
        await asyncio.gather(*runners, *self.tasks, return_exceptions=True)

    def _report_stopped(self) -> None:
        with contextlib.suppress(Exception):
            self.report.event("stopped", "companion stopping", handed_over=self._handed_over)

    async def _hand_over(self, why: str, can_brake: bool) -> bool:
        """`HandOver.hand_over`, bounded by `[safety] exit_timeout` and given up on `abandon`."""
        job = asyncio.create_task(self.handover.hand_over(why, can_brake=can_brake))
        quit_now = asyncio.create_task(self.abandon.wait())
        timeout = self.handover.hold_profile().exit_timeout  # per autopilot; [safety] exit_timeout overrides
        done, _ = await asyncio.wait([job, quit_now], timeout=timeout,
                                     return_when=asyncio.FIRST_COMPLETED)
        quit_now.cancel()
        if job in done:
            if job.exception() is None:
                return bool(job.result())
            log.error("hand-over failed", exc_info=job.exception())
            return False
        job.cancel()
        await asyncio.gather(job, return_exceptions=True)
        what = "a second signal" if self.abandon.is_set() else f"[safety] exit_timeout ({timeout:g} s)"
        with contextlib.suppress(Exception):
            self.report.event("error", f"hand-over to the autopilot given up on {what}; mode {self.link.state.mode}")
        return False


async def run(config: Config, *, stop: asyncio.Event | None = None, abandon: asyncio.Event | None = None) -> bool:
    """Run the service until `stop` is set (or forever), then hand the vehicle over; a set
    `abandon` gives the hand-over up. True when nothing was left to a failsafe."""
    return await Service(config, stop, abandon).run()
