"""Operator commands as explicit sequences: arm, takeoff, start, hold, resume, land, abort, disarm.

Which command is accepted in which state is `FlightState.refuse` (the table is in the README);
the sequences here talk to the autopilot through the MAVLink adapter, hand control to and
from `Control`, and missions to `Navigator`. A sequence that fails says why (`refused`,
with the autopilot's answer) and leaves the vehicle in a state it can be commanded from.
"""

from __future__ import annotations

import asyncio
import collections
import functools
import logging
import math
import time
from collections.abc import Iterable
from typing import Any

import numpy as np

from companion.config import Config, HoldProfile, hold_profile
from companion.control import SWAP_LATE, Control
from companion.flight import HOLDING_CONTROL, State
from companion.lag import LagEstimator, initial_lead
from companion.navigator import MAX_AHEAD, RETRY_MARGIN, Navigator
from companion.report import Reporter
from companion.runtime import Runtime
from companion.supervisor import (
    Armed,
    ArmRequested,
    ControlTaken,
    ControlTakenBack,
    DisarmedOnCommand,
    DisarmRequested,
    ExitBegan,
    ExitRequested,
    HandedOver,
    LandRequested,
    SequenceAborted,
    Stalled,
    StartBegan,
    StartEnded,
    Supervisor,
    TakeoffBegan,
    TakeoffInterrupted,
    TakingControl,
    TookOff,
)
from companion.wire.mavlink import (
    APM_MODES,
    MAV_LANDED_IN_AIR,
    MAV_LANDED_ON_GROUND,
    PX4_MODES,
    CommandFailed,
    MavlinkLink,
    Note,
)
from companion.wire.messages import Command
from companion.wire.px4_events import arming_report
from planner_core import Problem, allocate_times, plan, splice, takeoff_duration

log = logging.getLogger("companion")
S = State
LEAD_SLEW = 0.1  # s per s: how fast the auto lead follows the lag estimate (the setpoints run 10 % fast or slow)
# Modes that hold with no pilot input, per autopilot (docs/handover.md): never "pilot modes".
AUTONOMOUS_HOLDS = {"px4": ("LOITER",), "ardupilot": ("GUIDED", "BRAKE")}
TRACKING_SAMPLES = 3  # position samples in a row above the limit (0.1 s at 30 Hz) before acting
# The tracking measured in flight against [planner] tracking_allowance: an event when the RMS
# over the last TRACKING_WINDOW samples (or the largest error) passes this share of it.
TRACKING_WINDOW = 150  # position samples (~5 s at 30 Hz)
TRACKING_RMS_SHARE = 0.5
TRACKING_MAX_SHARE = 0.8


def in_mode(mode: str, state: Any) -> bool:
    return bool(state.mode == mode)


def at_rest(velocity: np.ndarray, threshold: float) -> bool:
    return bool(np.all(np.isfinite(velocity))) and float(np.linalg.norm(velocity)) <= threshold


class Commands:
    def __init__(self, cfg: Config, flight: Supervisor, control: Control, link: MavlinkLink, navigator: Navigator,
                 report: Reporter, runtime: Runtime | None = None) -> None:
        self.cfg = cfg
        self.flight = flight
        self.control = control
        self.link = link
        self.nav = navigator
        self.report = report
        self.runtime = runtime  # the planner's workers (the takeoff climb)
        self.task: asyncio.Task[None] | None = None  # the running arm/takeoff/start sequence
        self._settle_by: float | None = None  # loop time: the hand-over's vehicle settled by then
        # PX4's EVENTs heard (the service shares AutopilotWatch's): the last arming-check report
        self.events_heard: Iterable[Note] = link.state.notes
        # tracking: measured position against the setpoint of the measurement's time
        self.tracking_error: float | None = None
        self.tracking_error_max = 0.0  # since the service started
        self._over = 0  # consecutive samples above [planner] tracking_allowance
        self._tracking_said = False
        self._tracking_stop: asyncio.Task[None] | None = None
        self._recent_errors: collections.deque[float] = collections.deque(maxlen=TRACKING_WINDOW)
        self._nearing_said = False  # the tracking measured nears the allowance: said once per flight phase
        # lag compensation: the vehicle's lag behind the setpoints it is sent, from telemetry
        self.lag = LagEstimator(cap=cfg.setpoints.lead_max)
        self._leads: collections.deque[tuple[float, float]] = collections.deque()  # (t, lead) sampled
        self._lead_set_at: float | None = None
        self.lead_target: Any = None  # the setpoint thread (its `lead` is set here only: steer_lead)
        self._stall_task: asyncio.Task[None] | None = None  # what a stall of the companion set off

    def cancel_sequence(self) -> None:
        if self.task is not None and self.task is not asyncio.current_task() and not self.task.done():
            self.task.cancel()

    def take_control(self, reason: str) -> None:
        st = self.link.state
        self.control.take(st.position, float(st.attitude[2]), reason)
        self.flight.handle(ControlTaken())

    def release_control(self) -> None:
        """Stop commanding at once; what is left of the mission waits for `start`."""
        self.control.release()
        self.cancel_sequence()

    # -- dispatch -------------------------------------------------------------------------------

    async def on_command(self, cmd: Command, arrived: float) -> None:
        name, st = cmd.name, self.link.state
        why = self.flight.refuse(name, armed=st.armed, auto_arm=self.cfg.safety.auto_arm,
                                 has_mission=self.nav.has_mission(),
                                 reported_in_air=st.landed_state == MAV_LANDED_IN_AIR)
        if why is None and st.last_heartbeat == -math.inf:
            why = "no autopilot heartbeat yet"
        if why is None and name in ("arm", "takeoff", "start"):
            why = st.position_problem()
        if why is not None:
            self.report.refuse(name, why, by="companion")
            return
        self.report.event("accepted", f"command {name}", key="command", command=name)
        if name == "takeoff" and cmd.origin == "home" and st.home is None:
            self.report.refuse(name, "a takeoff altitude above home needs HOME_POSITION, which the autopilot has "
                               "not reported yet (send it without origin: above the ground where the vehicle stands)",
                               by="companion")
            return
        if name in ("arm", "takeoff", "start"):
            self.cancel_sequence()
            if name == "arm":
                body = self.arm()
            elif name == "takeoff":
                body = self.takeoff(cmd.altitude or self.cfg.safety.takeoff_altitude, cmd.origin)
            else:
                body = self.start(arrived)
            self.task = asyncio.create_task(self._sequence(name, body))
            return
        done = True
        if name == "hold":
            await self.nav.hold("hold command", arrived)
        elif name == "resume":
            await self.nav.resume(arrived)
            done = self.nav.interrupted is None
        elif name == "land":
            if await self.land():
                # `completed` once the vehicle is on the ground, not when the landing starts
                self.task = asyncio.create_task(self._sequence(name, self._until_on_ground()))
            return
        elif name == "abort":
            await self.abort(arrived)
        elif name == "disarm":
            done = await self.disarm()
        if done:
            self._completed(name)

    def _completed(self, name: str) -> None:
        """The command did what it says (`python -m companion send` exits 0 on this)."""
        self.report.event("completed", f"command {name} done ({self.flight.state.value})", key="command",
                          command=name)

    async def _sequence(self, name: str, coro: Any) -> None:
        try:
            await coro
        except CommandFailed as exc:
            # the companion's own checks say why; the autopilot's refusals say what failed
            reason = str(exc) if exc.by == "companion" else f"failed: {exc}"
            extra: dict[str, Any] = {}
            if exc.by == "autopilot" and exc.result is not None and name in ("arm", "takeoff", "start"):
                checks = arming_report(self.events_heard, time.monotonic())
                if checks is not None and checks[1]:
                    age, said = checks
                    reason += f"; PX4's arming checks ({age:.1f} s before): {'; '.join(said)}"
                    exc.reasons = tuple(dict.fromkeys((*exc.reasons, *said)))
                    extra["arming_checks"] = {"age_s": round(age, 2), "reasons": list(said)}
            self.report.refuse(name, reason, by=exc.by, **exc.fields(), **extra)
            self.flight.handle(SequenceAborted(f"{name} failed: {exc}", armed=self.link.state.armed))
        except asyncio.CancelledError:
            self.report.refuse(name, "cancelled before it completed", by="companion")
        else:
            self._completed(name)

    # -- sequences -------------------------------------------------------------------------------

    async def _take_follow_mode(self, reason: str) -> None:
        """Stream a hold at the measured position, then ask for OFFBOARD/GUIDED."""
        st = self.link.state
        self.flight.handle(TakingControl(reason))
        if st.autopilot == "px4":
            sent = self.link.sent_setpoints
            self.take_control(reason)
            # PX4 refuses OFFBOARD unless setpoints have been streaming for a while (COM_OF_LOSS_T-
            # based, 1 s in the docs): counted from the first setpoint that left, not from when
            # we asked for the stream, which a busy computer may start a few hundred ms late.
            started = time.monotonic() + 3.0
            while self.link.sent_setpoints == sent and time.monotonic() < started:
                await asyncio.sleep(0.005)
            await asyncio.sleep(1.1)
        await self.link.set_follow_mode()
        await self.link.wait_for(lambda s: s.in_follow_mode(), 3.0, "the autopilot to confirm OFFBOARD/GUIDED")
        if st.autopilot != "px4" and self.flight.airborne:
            self.take_control(reason)

    async def arm(self) -> None:
        st = self.link.state
        before = (st.base_mode, st.custom_mode, st.mode)
        await self._take_follow_mode("arm command")
        self.flight.handle(ArmRequested())
        try:
            await self.link.arm(True)
            await self.link.wait_for(lambda s: s.armed, 3.0, "the autopilot to report armed")
        except CommandFailed as exc:
            if st.armed or not before[2] or st.mode == before[2]:
                raise
            # Denied: leave the autopilot in the mode it was in, not in OFFBOARD/GUIDED.
            try:
                await self.link.restore_mode(before[0], before[1])
                await self.link.wait_for(lambda s: s.mode == before[2], 3.0, f"the autopilot to confirm {before[2]}")
            except CommandFailed as again:
                raise exc.chained(f"{exc}; and the previous mode {before[2]} was not restored: {again}") from exc
            raise exc.chained(f"{exc}; the autopilot is back in {before[2]}") from exc
        self.flight.handle(Armed(self.link.state.mode))

    def takeoff_target(self, altitude: float, origin: str = "ground") -> tuple[np.ndarray, str]:
        """Where a takeoff to `altitude` ends (NED, local frame), and what it is above.

        Above the ground where the vehicle stands (the z it last stood at disarmed, or where it
        is when on the ground), or above home (`origin` "home"): never `z = -altitude` in the
        local frame, whose origin is not the ground (PX4's ground is often at z = +1.5 m)."""
        st, fl = self.link.state, self.flight
        here = st.position.copy()
        if origin == "home" and st.home is not None:
            return np.array([here[0], here[1], float(st.home[2]) - altitude]), "home"
        on_ground = not fl.airborne and st.landed_state != MAV_LANDED_IN_AIR
        if on_ground or fl.ground_z is None:
            return here + np.array([0.0, 0.0, -altitude]), "the ground"
        return np.array([here[0], here[1], fl.ground_z - altitude]), "the ground"

    async def takeoff(self, altitude: float, origin: str = "ground") -> None:
        st = self.link.state
        if not st.armed:
            await self.arm()
        elif self.flight.state not in (S.READY, S.HOLDING):
            await self._take_follow_mode("takeoff command")
        target, above = self.takeoff_target(altitude, origin)
        self.flight.handle(TakeoffBegan(f"taking off to {altitude:.2f} m above {above} (local z {target[2]:.2f} m NED)"))
        tol = self.cfg.safety.arrival_tolerance
        if st.autopilot == "px4":
            await self._px4_climb(target)
        else:
            self.control.pause()
            # ArduPilot's takeoff altitude is above home
            home_z = float(st.home[2]) if st.home is not None else float(st.position[2])
            await self.link.takeoff(max(0.1, home_z - float(target[2])))
            rest = self.cfg.safety.rest_speed
            await self.link.wait_for(lambda s: abs(s.position[2] - target[2]) <= tol and at_rest(s.velocity, rest),
                                     10.0 + altitude / 0.3, f"altitude {altitude:.2f} m, at rest")
            self.take_control("takeoff complete")
        self.flight.handle(TookOff(f"airborne at {altitude:.2f} m above {above}: holding"))
        pending = self.nav.pending
        if pending is not None and pending.autostart and not self.flight.starting:
            await self.nav.fly(pending, None)

    async def _px4_climb(self, target: np.ndarray) -> None:
        """A verified vertical climb streamed in OFFBOARD (PX4 has no GUIDED-style takeoff for us)."""
        bounds = self.nav.default_bounds()  # within the autopilot's limits
        # split as far ahead as planning takes in this service; a plan that comes late is planned
        # again once, further ahead (as Navigator._swap_at_split does for missions)
        ahead = self.nav.split_ahead_for(2)
        for attempt in range(2):
            base = self.control.active
            assert base is not None
            t_split = self.control.committed() + ahead
            jet = base.jet(t_split)
            points = np.vstack([jet[0], target])
            climb = target - jet[0]
            height = float(np.linalg.norm(climb))
            if height > 1e-3 and at_rest(jet[1], self.cfg.safety.rest_speed):
                # the fastest rest-to-rest climb the planner certifies (issue 12); from a moving
                # start the planner's recovery stretches it if it must
                durations = np.array([takeoff_duration(height, bounds, up=tuple(climb / height))])
            else:
                durations = np.diff(allocate_times(points, bounds, t0=t_split))
            problem = Problem.from_waypoints(points, durations, bounds, initial=jet, t0=t_split)
            t0 = time.monotonic()
            assert self.runtime is not None
            result = await self.runtime.plan(plan, problem)
            took = time.monotonic() - t0
            if not result.ok or result.trajectory is None:
                raise CommandFailed(f"no verified climb: {result.message}", by="companion")
            if self.control.swap(splice(base, result.trajectory), t_split, None, "takeoff"):
                break
            if not self.control.flying:
                raise CommandFailed("control was released during the climb's planning", by="companion")
            if self.control.refusal != SWAP_LATE or attempt == 1:
                raise CommandFailed(f"climb not swapped in: {self.control.refusal}"
                                    + (f" (planning took {took:.2f} s, twice)" if attempt == 1 else ""), by="companion")
            ahead = min(max(2.0 * ahead, RETRY_MARGIN * took + 0.1), MAX_AHEAD)
        tol, rest = self.cfg.safety.arrival_tolerance, self.cfg.safety.rest_speed
        end = result.trajectory.t_end
        await self.link.wait_for(
            lambda s: self.control.flying and self.control.now() >= end and abs(s.position[2] - target[2]) <= tol
            and at_rest(s.velocity, rest), end - self.control.now() + 10.0, "the climb to finish, at rest")

    async def start(self, arrived: float) -> None:
        self.flight.handle(StartBegan())
        try:
            await self._start(arrived)
        finally:
            self.flight.handle(StartEnded())

    async def _start(self, arrived: float) -> None:
        st = self.link.state
        if not st.armed:
            await self.takeoff(self.cfg.safety.takeoff_altitude)
        elif self.flight.state in (S.PILOT, S.FAILSAFE, S.IDLE):
            if not self.flight.airborne and st.landed_state != MAV_LANDED_IN_AIR and st.autopilot != "px4":
                raise CommandFailed("vehicle is on the ground: send 'takeoff' first", by="companion")
            await self._take_follow_mode("start command: taking control")
            self.flight.handle(ControlTakenBack(self.link.state.mode))
        if self.flight.state is S.READY and not self.flight.airborne:
            await self.takeoff(self.cfg.safety.takeoff_altitude)
        nav = self.nav
        if nav.pending is not None:
            await nav.fly(nav.pending, arrived)
        elif nav.interrupted is not None:
            await nav.resume(arrived)

    async def land(self) -> bool:
        """The autopilot lands (NAV_LAND / LAND mode), from any state in which the vehicle may
        be in the air: our modes, a pilot's, a failsafe's, or after a restart."""
        self.cancel_sequence()
        self.control.forget()
        self.control.release()
        self.flight.handle(LandRequested())
        try:
            await self.link.land()
        except CommandFailed as exc:
            self.report.refuse("land", f"failed: {exc}", by="autopilot", **exc.fields())
            return False
        return True

    async def _until_on_ground(self) -> None:
        """The landing ends on the ground: disarmed, or EXTENDED_SYS_STATE on-ground (fresh)."""
        st = self.link.state
        height = 0.0 if self.flight.ground_z is None or not st.has_position else \
            max(0.0, self.flight.ground_z - float(st.position[2]))

        def on_ground(s: Any) -> bool:
            return (not s.armed or (s.landed_state == MAV_LANDED_ON_GROUND
                                    and time.monotonic() - s.last_landed_state < 3.0))

        await self.link.wait_for(on_ground, 30.0 + height / 0.3, "the vehicle to be on the ground")

    async def abort(self, arrived: float) -> None:
        self.cancel_sequence()
        state = self.flight.state
        if state in HOLDING_CONTROL or (state is S.TAKEOFF and self.control.streaming):
            await self.nav.abort(arrived)
        else:
            self.control.forget()
            self.flight.handle(SequenceAborted("abort command", armed=self.link.state.armed))
        self.report.event("aborted", "mission and pending commands cancelled")

    # -- tracking -------------------------------------------------------------------------

    @property
    def lag_estimate(self) -> float | None:
        return self.lag.estimate

    def _brake_name(self) -> str:
        return "[safety] tracking_brake" if self.cfg.safety.tracking_brake else "[planner] tracking_allowance"

    def check_tracking(self, measured_at: float) -> None:
        """Each position sample: the time-aligned tracking error; above `[planner]
        tracking_allowance` (the margin the obstacles are inflated by) for TRACKING_SAMPLES
        samples in a row while a plan is flown: brake to a verified stop and hold (holding
        already: say so once), with the figures. The measured RMS or max nearing the allowance
        is said too (once per flight phase): the certificate assumes the allowance holds."""
        st, ctl, fl = self.link.state, self.control, self.flight
        err = ctl.tracking_error(st.position, measured_at) if fl.controlling else None
        self.tracking_error = err
        # Judged only in the air, flying or holding a plan of ours after the takeoff's climb
        # (`flying_ours`: READY, STREAMING, HOLDING, BRAKING and airborne): on the ground and
        # while arming, an estimate not yet settled (PX4 before ready: z wandering by up to 2 m)
        # is no tracking error, and the climb is PX4's to shape (it trails by up to 2.5 m).
        if err is None or not fl.flying_ours:
            self._over = 0
            self._recent_errors.clear()
            self._nearing_said = False
            self.lag.hold()
            return
        self.tracking_error_max = max(self.tracking_error_max, err)
        self._estimate_lag(measured_at)
        limit = self.cfg.safety.tracking_brake or self.cfg.planner.tracking_allowance
        if limit <= 0.0:  # no allowance: no inflation and no brake (planning tests, benches)
            return
        self._check_nearing(err, limit)
        self._over = self._over + 1 if err > limit else 0
        if self._over == 0:
            self._tracking_said = False
            return
        if self._over < TRACKING_SAMPLES or self._tracking_said:
            return
        if self._tracking_stop is not None and not self._tracking_stop.done():
            return
        self._tracking_said = True
        ref = ctl.reference(measured_at)
        flying = fl.state is S.STREAMING and fl.airborne
        what = "braking to a stop and holding" if flying else "holding already"
        self.report.event("tracking", f"tracking error {err:.2f} m over {self._brake_name()} {limit:.2f} m "
                          f"for {self._over} samples: {what}",
                          error=round(err, 3), limit=limit, samples=self._over,
                          position=[round(float(x), 3) for x in st.position],
                          setpoint=None if ref is None else [round(float(x), 3) for x in ref])
        if flying:
            self._tracking_stop = asyncio.get_running_loop().create_task(
                self.nav.hold(f"tracking error {err:.2f} m > {self._brake_name()} {limit:.2f} m", None))

    def _check_nearing(self, err: float, limit: float) -> None:
        if not self.flight.flying_ours:
            return
        self._recent_errors.append(err)
        if self._nearing_said or len(self._recent_errors) < TRACKING_WINDOW // 3:
            return
        e = np.asarray(self._recent_errors)
        rms, worst = float(np.sqrt(np.mean(e * e))), float(e.max())
        if rms < TRACKING_RMS_SHARE * limit and worst < TRACKING_MAX_SHARE * limit:
            return
        self._nearing_said = True
        allowance = self.cfg.planner.tracking_allowance
        if self.cfg.safety.tracking_brake:  # the brake is set apart from the allowance: name both
            near = "the brake"
            advice = (f"[planner] tracking_allowance {allowance:.2f} m is what the obstacles are inflated by, "
                      "the track beyond it is outside what was certified: lower the bounds, or raise the "
                      "allowance")
        else:
            near, advice = "the allowance", "raise the allowance or lower the bounds"
        self.report.event("tracking_margin", f"tracking measured near {near}: RMS {rms:.2f} m, max {worst:.2f} m over "
                          f"the last {len(e)} samples, {self._brake_name()} {limit:.2f} m (warned at "
                          f"{TRACKING_RMS_SHARE:.0%} RMS / {TRACKING_MAX_SHARE:.0%} max): {advice}",
                          rms=round(rms, 3), max=round(worst, 3), limit=limit, limit_name=self._brake_name(),
                          tracking_allowance=allowance, samples=len(e))

    def _estimate_lag(self, measured_at: float) -> None:
        """The vehicle's lag behind its setpoints (companion.lag: a least-squares fit over a
        sliding window of motion, smoothed, held at rest, at most [setpoints] lead_max). With
        `setpoints.lead = "auto"` the setpoints lead by it."""
        ctl = self.control
        active, t_base = ctl.active, ctl.t_base
        if not self.flight.flying_ours or not ctl.streaming or active is None or t_base is None:
            self.lag.hold()
            self._lead_set_at = None
            return
        lead_now = float(getattr(self.lead_target, "lead", 0.0))
        jet = ctl.reference_jet(measured_at + lead_now)
        if jet is None:
            return
        speed = float(np.linalg.norm(jet[1]))
        leads = self._leads
        leads.append((measured_at, lead_now))
        while len(leads) > 2 and leads[1][0] < measured_at - self.cfg.setpoints.lead_max - 0.5:
            leads.popleft()
        lt, lv = np.array([x[0] for x in leads]), np.array([x[1] for x in leads])

        def stream_at(times: np.ndarray) -> np.ndarray:
            # the setpoint sent at time t was the plan at t + the lead of then
            ts = np.clip(times - t_base + np.interp(times, lt, lv), active.t0, active.t_end)
            return np.asarray(active.evaluate(ts, 0), dtype=float)

        self.lag.add(measured_at, self.link.state.position, speed, stream_at)
        est = self.lag.estimate
        if est is not None and self.cfg.setpoints.lead == "auto" and self.lead_target is not None:
            # towards the estimate at most LEAD_SLEW s per s: a jump of the lead would make the
            # setpoints jump along the plan
            last = self._lead_set_at if self._lead_set_at is not None else measured_at
            step = LEAD_SLEW * max(0.0, measured_at - last)
            want = min(est, self.cfg.setpoints.lead_max)
            self._set_lead(lead_now + max(-step, min(step, want - lead_now)))
        self._lead_set_at = measured_at

    def steer_lead(self, target: Any) -> None:
        """Set the lead of `target` (the setpoint thread or process), from now on only here: the
        configured one, or with `setpoints.lead = "auto"` the initial one, then the estimate."""
        sp = self.cfg.setpoints
        self.lead_target = target
        self._set_lead(self.initial_lead() if sp.lead == "auto" else float(sp.lead))

    def initial_lead(self) -> float:
        """The auto lead before the estimate has seen motion: `[setpoints] lead_initial`, by
        default the lag measured on the autopilot linked (companion.lag.MEASURED_LAG)."""
        sp = self.cfg.setpoints
        return initial_lead(sp.lead_initial, self.link.state.autopilot, sp.lead_max)

    def autopilot_found(self) -> None:
        """Link-up (or a reconnect): the autopilot is known. With `lead = "auto"` and no
        estimate yet, the lead starts at that autopilot's measured lag (PX4 SIH lags ~0.33 s,
        ArduCopter ~0.06 s: from ArduCopter's, a PX4 vehicle's first seconds of motion trail
        the plan by ~0.27 s x the speed). Not while streaming: the setpoints would jump."""
        if (self.cfg.setpoints.lead == "auto" and self.lag.estimate is None and self.lead_target is not None
                and not self.control.streaming):
            self._set_lead(self.initial_lead())

    def _set_lead(self, lead: float) -> None:
        """The one writer of the setpoints' lead."""
        self.lead_target.lead = lead

    # -- the hand-over on exit -------------------------------------------------------------

    async def hand_over(self, reason: str, *, can_brake: bool = True) -> bool:
        """Leave the vehicle to the autopilot's own control before the service exits.

        In the air and in control: brake to a verified stop (when the setpoint stream still
        works), then hand over as `[safety] on_exit` says: "hold" is an autonomous hold that
        needs no pilot (PX4 AUTO.LOITER; ArduPilot GUIDED holding a position target at the
        stop point, or BRAKE when no setpoint can be sent; a configured pilot mode only when a
        pilot is known present: docs/handover.md), "land" or "rtl". The hold is confirmed by
        watching the vehicle (`hold_confirm` s within the altitude and speed tolerances), not
        only its mode. Armed on the ground in control: disarm. Returns True when the vehicle
        was left holding (or landing, as asked), False when the hand-over failed or the
        vehicle moved."""
        fl, st = self.flight, self.link.state
        self.cancel_sequence()
        fl.handle(ExitBegan(reason, flying=self.control.flying))
        if not fl.controlling or not st.armed or fl.link_lost:
            self.control.release()
            fl.handle(SequenceAborted(f"{reason}: sequence interrupted", armed=st.armed))
            return not (fl.link_lost and fl.controlling)
        airborne = fl.airborne or st.landed_state == MAV_LANDED_IN_AIR or fl.state is S.TAKEOFF
        if not airborne:
            fl.handle(DisarmRequested())
            try:
                await self.link.arm(False)
                await self.link.wait_for(lambda s: not s.armed, 3.0, "the autopilot to report disarmed")
            except CommandFailed as exc:
                self.report.event("error", f"{reason}: disarm on the ground failed ({exc}); handing over instead")
            else:
                self.control.release()
                fl.handle(DisarmedOnCommand(f"{reason}: disarmed on the ground"))
                return True
        fl.handle(TakeoffInterrupted(f"{reason}: takeoff interrupted"))
        braked = False
        self._settle_by = None
        if can_brake and self.control.streaming and fl.state in HOLDING_CONTROL:
            braked = await self._brake_for_exit(reason)
        return await self._request_exit_mode(reason, stream_works=can_brake and self.control.streaming and braked)

    def hold_profile(self) -> HoldProfile:
        """The hand-over's thresholds for this autopilot, `[safety]` keys overriding them."""
        return hold_profile(self.cfg.safety, self.link.state.autopilot)

    async def _brake_for_exit(self, reason: str) -> bool:
        """A verified stop, flown to rest; True when the vehicle is at rest at its end."""
        try:
            await asyncio.wait_for(self.nav.hold(f"{reason}: stopping before the hand-over", None), 2.0)
        except TimeoutError:  # a plan change held the navigator: hold where the vehicle is
            log.warning("braking for the hand-over timed out; holding at the measured position")
            if self.control.flying:
                self.control.hold_here(self.link.state.position)
        ctl, rest = self.control, self.cfg.safety.rest_speed
        end = ctl.active.t_end if ctl.active is not None else 0.0
        left = max(0.0, end - (ctl.now() if ctl.flying else 0.0))
        # the autopilot's own braking trails the stop (PX4 ~0.3 s late): `settle` s are allowed
        self._settle_by = asyncio.get_running_loop().time() + left + self.hold_profile().settle
        try:
            await self.link.wait_for(
                lambda s: not ctl.flying or (ctl.now() >= end and at_rest(s.velocity, rest)),
                left + self.hold_profile().settle, "the vehicle to stop")
        except CommandFailed:
            return False
        return ctl.flying

    def exit_plan(self, stream_works: bool) -> tuple[str, str]:
        """(mode to ask for, why) for `[safety] on_exit`. "GUIDED" means: stay in GUIDED with
        a position target at the stop point (ArduPilot). Never a pilot mode unless configured
        and a pilot is known present (docs/handover.md)."""
        st, sc = self.link.state, self.cfg.safety
        if sc.on_exit == "land":
            return "LAND", "[safety] on_exit = land"
        if sc.on_exit == "rtl":
            return "RTL", "[safety] on_exit = rtl"
        pilot = sc.exit_pilot_mode
        known = PX4_MODES if st.autopilot == "px4" else APM_MODES
        if pilot and pilot in known and pilot not in AUTONOMOUS_HOLDS.get(st.autopilot or "", ()):
            if sc.pilot_present or st.pilot_sticks_live():
                how = "[safety] pilot_present" if sc.pilot_present else "RC_CHANNELS: a live transmitter, throttle centred"
                return pilot, f"[safety] exit_pilot_mode = {pilot}, a pilot is known present ({how})"
            self.report.event("handover", f"[safety] exit_pilot_mode {pilot} not used: no pilot is known present "
                              "(no [safety] pilot_present, no RC_CHANNELS with a live transmitter at mid-stick); "
                              "an autonomous hold instead", mode=pilot, pilot_mode_refused=True)
        if st.autopilot == "px4":
            return "LOITER", "AUTO.LOITER holds without a pilot"
        if stream_works:
            return "GUIDED", "GUIDED holds a position target with no timeout"
        return "BRAKE", "BRAKE holds until the mode is changed (setpoints cannot be sent)"

    async def _request_exit_mode(self, reason: str, stream_works: bool = False) -> bool:
        st = self.link.state
        wanted, why = self.exit_plan(stream_works)
        self.flight.handle(ExitRequested())  # our mode changes: not a pilot takeover
        fallbacks = [wanted] + ([] if wanted in ("LAND", "BRAKE") or st.autopilot == "px4" else ["BRAKE"])
        fallbacks += [] if wanted == "LAND" else ["LAND"]
        for mode in fallbacks:
            try:
                if mode == "GUIDED":
                    if not st.in_follow_mode() or self.control.active is None or not self.control.flying:
                        raise CommandFailed("not in GUIDED with a verified stop to hold")
                    stop = self.control.jet(self.control.active.t_end)[0]
                    self.control.release()  # the stream stops: the position target is the last word
                    self.link.send_position_target(stop, self.yaw_now())
                else:
                    await self.link.set_mode(mode)
                    await self.link.wait_for(functools.partial(in_mode, mode), 3.0, f"the autopilot to confirm {mode}")
            except CommandFailed as exc:
                self.report.event("error", f"{reason}: hand-over to {mode} failed: {exc}", mode=st.mode)
                why = f"after the hand-over to {mode} failed"
                continue
            self.control.release()
            self.flight.handle(HandedOver(reason, st.mode, landing=mode == "LAND"))
            if mode in ("LAND", "RTL"):
                self.report.event("handover", f"{reason}: the autopilot {'lands' if mode == 'LAND' else 'returns'} "
                                  f"in {st.mode} ({why})", mode=st.mode, reason=reason, held=None)
                return True
            return await self._confirm_hold(reason, mode, why)
        return False

    def yaw_now(self) -> float:
        """The heading last commanded (the measured one when nothing was sent)."""
        sp = self.control.last_sp
        return float(sp.yaw) if sp is not None else float(self.link.state.attitude[2])

    async def _confirm_hold(self, reason: str, mode: str, why: str) -> bool:
        """Watch the vehicle for the profile's `confirm` s (`hold_profile`: PX4 and ArduPilot
        differ, docs/handover.md): the hold is confirmed only if the mode stays, the vehicle
        stays armed, its altitude within `altitude_tolerance` of where the hold began and, once
        settled (its speed once under the tolerance, or `settle` s after the verified stop's
        end), its speed under `speed_tolerance`."""
        st, pr = self.link.state, self.hold_profile()
        loop = asyncio.get_running_loop()
        z0, mode_now = float(st.position[2]), st.mode
        worst_dz, worst_v = 0.0, 0.0
        start = loop.time()
        settle_by = self._settle_by if self._settle_by is not None else start + pr.settle
        # `confirm` s, longer only while the vehicle has not settled (then up to 1 s past the settle time)
        done_by, latest = start + pr.confirm, max(start + pr.confirm, min(settle_by, start + pr.settle) + 1.0)
        settled = False
        problem = None
        while loop.time() < latest and not (settled and loop.time() >= done_by):
            await asyncio.sleep(0.05)
            dz = float(st.position[2]) - z0
            speed = float(np.linalg.norm(st.velocity))
            worst_dz = dz if abs(dz) > abs(worst_dz) else worst_dz
            worst_v = max(worst_v, speed)
            settled = settled or speed <= pr.speed_tolerance or loop.time() >= settle_by
            if not st.armed:
                problem = "the vehicle disarmed"
            elif st.mode != mode_now:
                problem = f"the autopilot left {mode_now} for {st.mode}"
            elif abs(dz) > pr.altitude_tolerance:
                problem = f"the vehicle {'descends' if dz > 0 else 'climbs'}: {abs(dz):.2f} m from where the hold began"
            elif settled and speed > pr.speed_tolerance:
                vz = float(st.velocity[2])
                how = f" ({'descending' if vz > 0 else 'climbing'} at {abs(vz):.2f} m/s)" if abs(vz) >= 0.5 * speed else ""
                problem = f"the vehicle moves at {speed:.2f} m/s{how}"
            if problem is not None:
                break
        watched = round(loop.time() - start, 2)
        fields = {"mode": st.mode, "reason": reason, "altitude_change": round(worst_dz, 3),
                  "speed_max": round(worst_v, 3), "watched_s": watched,
                  "limits": {"altitude": pr.altitude_tolerance, "speed": pr.speed_tolerance,
                             "settle_s": pr.settle, "confirm_s": pr.confirm}}
        if problem is not None:
            msg = (f"{reason}: the hand-over to {mode_now} does not hold: {problem} (limits "
                   f"{pr.altitude_tolerance:g} m, {pr.speed_tolerance:g} m/s after {pr.settle:g} s to settle, "
                   f"over {pr.confirm:g} s; [safety] hold_* keys)")
            log.error("%s", msg)
            self.report.event("handover", msg, held=False, **fields)
            return False
        self.report.event("handover", f"{reason}: the autopilot holds the vehicle in {mode_now} ({why}): "
                          f"altitude within {abs(worst_dz):.2f} m, speed under {worst_v:.2f} m/s for "
                          f"{watched:g} s", held=True, **fields)
        return True

    async def disarm(self) -> bool:
        self.flight.handle(DisarmRequested())
        self.release_control()
        try:
            await self.link.arm(False)
        except CommandFailed as exc:
            self.report.refuse("disarm", f"failed: {exc}", by="autopilot", **exc.fields())
            return False
        self.flight.handle(DisarmedOnCommand("disarmed on command"))
        return True

    # -- after a stall of the companion ------------------------------------------------------

    def after_stall(self, reason: str) -> asyncio.Task[None] | None:
        """The companion stalled (its loop or the setpoint thread): setpoints were withheld
        from the stall on. Stop commanding (FAILSAFE: control is taken back only by `start`)
        and, if the autopilot still flies in our mode, ask it for an autonomous hold (PX4
        AUTO.LOITER, ArduPilot BRAKE) rather than leave it to its offboard-loss failsafe.
        Returns the hold request's task, if any."""
        fl, st = self.flight, self.link.state
        if not fl.controlling:
            return None
        was = fl.state
        in_air = fl.airborne or st.landed_state == MAV_LANDED_IN_AIR or was is S.TAKEOFF
        ours = st.armed and st.in_follow_mode()
        fl.handle(Stalled(reason))
        if not (ours and in_air):
            return None
        self._stall_task = asyncio.get_running_loop().create_task(self._hold_after_stall(reason))
        return self._stall_task

    def hold_after_stall(self, reason: str) -> str:
        """A stall after which the autopilot still flies our plan: stop the mission and hold
        (braking to a verified stop; what is left waits for `resume`). Says what it did."""
        fl = self.flight
        if fl.state is S.STREAMING and fl.airborne and self.control.streaming:
            self._stall_task = asyncio.get_running_loop().create_task(self.nav.hold(reason, None))
            return "stopping the mission and holding (send 'resume' to continue)"
        return "in control as before" if fl.controlling else "not in control"

    async def _hold_after_stall(self, reason: str) -> None:
        """An autonomous hold (never a pilot mode: no pilot is known): PX4 AUTO.LOITER,
        ArduPilot BRAKE (it stops the vehicle at its own deceleration and holds until the mode
        is changed; no verified stop of ours is flying after a stall)."""
        st = self.link.state
        mode = "LOITER" if st.autopilot == "px4" else "BRAKE"
        try:
            await self.link.set_mode(mode)
            await self.link.wait_for(lambda s: s.mode == mode, 3.0, f"the autopilot to confirm {mode}")
        except CommandFailed as exc:
            self.report.event("error", f"{reason}: asking the autopilot to hold ({mode}) failed: {exc}",
                              mode=st.mode, **exc.fields())
            return
        self.report.event("handover", f"{reason}: the autopilot holds the vehicle in {st.mode}", mode=st.mode,
                          reason=reason, cause="companion")
