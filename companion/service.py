"""The companion service: wiring only. One asyncio loop per vehicle.

Zenoh in (mission, obstacles, change, command) -> `Inbound` (inbound.py: `wire.messages.read`,
typed, NED) -> one handler per kind -> planning in workers -> a verified trajectory swapped in by `Control` ->
the setpoint thread -> MAVLink out. Telemetry comes back over MAVLink and goes out on Zenoh.

The parts, each the one owner of what it holds:
- `Supervisor` (supervisor.py): the state and every flag about the vehicle's situation
  (flight.py), changed only by the events the other parts submit to it;
- `Control` (control.py): what is flown: the mission's route, the trajectory the setpoint
  thread flies and its time base, changed together; what is left of a mission (loaded,
  interrupted);
- `Navigator` (navigator.py): planning missions, changes and pop-ups in flight; the obstacles;
  its parts `MissionStart` (mission_start.py: accepted, started, improved), `Replans`
  (replans.py: changes, pop-ups, the fleet) and the one retry loop `SplitSwap` (split_swap.py);
- `Commands` (commands.py): the command sequences; `HandOver` (handover.py): leaving the
  vehicle to the autopilot; `Tracking` (tracking.py): the tracking error and the lead;
  `AutopilotWatch` (autopilot.py): reports;
- `StallWatch` (stalls.py): the companion's own stalls; `StatusReport` (status.py): the status;
- `Runtime` (runtime.py): executors; `Reporter` (report.py): events.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
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
from companion.inbound import Inbound
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
    SetpointSender,
    Tick,
    YawPolicy,
    sleep_until,
)
from companion.stalls import StallWatch
from companion.status import StatusReport
from companion.supervisor import Supervisor
from companion.tracking import Tracking
from companion.wire import encode as enc
from companion.wire.mavlink import MavlinkLink
from companion.wire.messages import (
    warm_validators,
)
from companion.wire.zenoh import ZenohIO
from planner_core import FloatArray, Trajectory, hold

log = logging.getLogger("companion")


def _tap_decisions(svc: Service) -> None:
    """Every call of the decisions' rules shown to the recorder, for replay (issue 23)."""
    tap = svc.tap
    svc.watch.connect(observe=tap.autopilot_step)  # the autopilot watch's
    svc.control.observe_swap = tap.swap  # every swap decided
    svc.tracking.connect(observe=tap.tracking_step)  # the tracking error's
    svc.navigator.split.observe = tap.split_step  # every plan made in flight: where it split, again
    svc.navigator.budget.observe = tap.budget_step  # how far ahead, how big a search
    svc.deconfliction.observe = tap.commit_step  # the fleet's commit protocol
    svc.deconfliction.observe_clock = tap.clock_sample  # and its clock check
    svc.navigator.brakes.observe = tap.race_step  # every pop-up obstacle and its race
    svc.commands.observe = tap.command_step  # the operator commands' sequences
    svc.stalls.observe = tap.stall_step  # the companion's own stalls
    svc.handover.observe = tap.hold_step  # whether the autopilot holds after a hand-over
    svc.navigator.choices.observe = tap.choice_step  # which plan a start, a replan, a stop asks for


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
        # where the autopilot's local frame sits in the fleet frame ([fleet] origin; companion.fleet)
        self.fleet = FleetFrame(cfg.fleet)
        # the other vehicles' trajectories and the commit protocol ([fleet] separation; companion.deconfliction)
        self.deconfliction = Deconfliction(cfg, self.fleet, lambda: self.control.t_base, self._publish_proposal,
                                           self.report.event)
        # the autopilot's own limits: read at link-up and after a reconnect, planned within
        self.limits = LimitsWatch(cfg, self.link, self.report)
        self.navigator = Navigator(cfg, self.flight, self.control, self.runtime, self.report, self._position,
                                   self.limits, self.deconfliction)
        self.commands = Commands(cfg, self.flight, self.control, self.link, self.navigator, self.report, self.runtime)
        self.tracking = Tracking(cfg, self.flight, self.control, self.link, self.navigator, self.report)
        self.handover = HandOver(cfg, self.flight, self.control, self.link, self.navigator, self.report,
                                 self.commands.cancel_sequence)
        # the companion's own stalls: the loop's beat, setpoints that stop leaving
        self.stalls = StallWatch(cfg, self.stop, self.report, self.link, self.control, self.flight, self.sender,
                                 self.handover)
        self.sender.liveness = self.stalls.liveness
        # what the supervisor decides to stop is stopped here: the stream, and any command sequence
        self.flight.connect(release=self.commands.release_control, stop_stream=self.control.release,
                            observe=self.tap.transition)  # every transition recorded, for replay (issue 23)
        self.watch = AutopilotWatch(cfg, self.flight, self.link, self.report,
                                    on_position=self.tracking.check_tracking, stalled=self.stalls.stalled)
        _tap_decisions(self)
        self.link.on_message = self._on_mavlink
        self.deconfliction.on_replan = self.navigator.fleet_replan
        self.deconfliction.on_clock_off = self.navigator.fleet_stop
        self.commands.events_heard = self.watch.events_heard  # the arming-check report, for refusals
        self.watch.on_link_up = self._link_up
        self.inbound = Inbound(cfg, self.stop, self.report, self.link, self.fleet, self.runtime, self.tap,
                               self.navigator, self.commands)
        self.link.on_ignored = self.inbound.mavlink_ignored
        # lag compensation: a fixed lead, or "auto" (set by Tracking from its estimate)
        self.tracking.steer_lead(self.sender)
        self.zio: ZenohIO | None = None
        self.notifier = Notifier()
        self.gc = GcPacer()
        self.loop: asyncio.AbstractEventLoop | None = None
        self.status_report = StatusReport(
            cfg, flight=self.flight, link=self.link, control=self.control, navigator=self.navigator,
            tracking=self.tracking, sender=self.sender, limits=self.limits, gc=self.gc, stalls=self.stalls,
            tap=self.tap, fleet=self.fleet, deconfliction=self.deconfliction,
            session=lambda: self.zio.zid if self.zio is not None else None)
        self._traj_seq = 0
        self._traj_published = 0
        self._traj_bytes: bytes | None = None
        self._sender_failure: asyncio.Future[None] | None = None
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
            # their status query (companion.cli_send, companion.cli_watch)
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

    def status(self) -> dict[str, Any]:
        return self.status_report.build()

    def _on_mavlink(self, kind: str, msg: Any) -> None:
        self.watch.on_message(kind, msg)
        if kind in ("GPS_GLOBAL_ORIGIN", "HOME_POSITION") and self.fleet.enabled:
            st = self.link.state
            said = self.fleet.update(st.gps_origin, st.home_lla, st.home)
            if said is not None:
                self.report.event("fleet_frame", said, **(self.fleet.status() or {}))

    # -- the autopilot found --------------------------------------------------------------------

    def _link_up(self, why: str) -> None:
        """The autopilot found (link-up, reconnect): its limits read, the lead it starts with."""
        self.limits.read(why)
        self.tracking.autopilot_found()

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
        self.navigator.budget.measured(time.monotonic() - t0, 2)
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
                for t in [*inbound, *self.inbound.tasks]:
                    t.cancel()
                await asyncio.gather(*inbound, *self.inbound.tasks, return_exceptions=True)
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
        self.inbound.attach(self.zio)
        self.zio.tap = self.tap
        undo.callback(self.tap.close)
        self.tap.open()
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
        self.stalls.liveness.beat()  # the warm-up above is not a stall
        undo.callback(self.sender.stop)
        self.sender.start(rtsched.starter())
        undo.callback(self.control.release)  # nothing is streamed once the sender stops
        if isinstance(self.sender, SetpointProcess):
            self.link.use_writer(self.sender)
        log.info("setpoint %s: %.0f Hz, %s scheduling", "process" if self.cfg.setpoints.process else "thread",
                 self.cfg.setpoints.rate_hz, self.sender.scheduling)
        periodic = [asyncio.create_task(c) for c in (self.heartbeat_loop(), self.telemetry_loop(), self.status_loop(),
                                                       self.stalls.setpoint_watchdog(),
                                                       self.stalls.loop_liveness())]
        if self.deconfliction.enabled:
            periodic.append(asyncio.create_task(self.fleet_loop()))
        inbound = [asyncio.create_task(c) for c in (self.inbound.inbox_loop(), self.inbound.ordered_loop())]
        sender = asyncio.ensure_future(self._sender_failure)
        runners: list[asyncio.Future[Any]] = [*periodic, *inbound, sender]
        self._runners = runners
        self.notifier.ready(f"vehicle {self.cfg.vehicle.id}: zenoh and mavlink up")
        self.report.event("started", f"companion for {self.cfg.vehicle.id} started", mavlink=self.cfg.mavlink.url)
        return runners, inbound, sender

    async def _cancel(self) -> None:
        seq = self.commands.task
        runners = self._runners
        handlers = self.inbound.tasks
        for t in [*runners, *handlers, *([seq] if seq else [])]:
            t.cancel()
        await asyncio.gather(*runners, *handlers, return_exceptions=True)

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
