"""Leaving the vehicle to the autopilot's own control: on exit, and after a stall of the companion.

On exit (`hand_over`): brake to a verified stop, then hand over as `[safety] on_exit` says and
confirm the hold by watching the vehicle, with each autopilot's thresholds (`hold_profile`,
docs/handover.md). After a stall: stop the mission and hold, or, when setpoints were withheld
too long, ask the autopilot for an autonomous hold. Never a pilot mode unless a pilot is known
present. Each autopilot's hold thresholds (HOLD_PROFILES, measured on the simulators) live here too.
"""

from __future__ import annotations

import asyncio
import functools
import itertools
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.config import Config, SafetyConfig
from companion.control import Control
from companion.flight import HOLDING_CONTROL, State
from companion.hold_rules import Action as HoldAction
from companion.hold_rules import Began, Fails, HoldRules, HoldState, Seen, Watch, hold_step
from companion.hold_rules import Observation as HoldObservation
from companion.navigator import Navigator
from companion.report import Reporter
from companion.rule_run import RuleRun
from companion.supervisor import (
    DisarmedOnCommand,
    DisarmRequested,
    ExitBegan,
    ExitRequested,
    HandedOver,
    SequenceAborted,
    Stalled,
    Supervisor,
    TakeoffInterrupted,
)
from companion.wire.mavlink import MavlinkLink
from companion.wire.vehicle import APM_MODES, MAV_LANDED_IN_AIR, PX4_MODES, CommandFailed

log = logging.getLogger("companion")
S = State
# Modes that hold with no pilot input, per autopilot (docs/handover.md): never "pilot modes".
AUTONOMOUS_HOLDS = {"px4": ("LOITER",), "ardupilot": ("GUIDED", "BRAKE")}


@dataclass(frozen=True)
class HoldProfile:
    """How the hand-over's hold is confirmed on one autopilot (docs/handover.md)."""
    settle: float  # s after the verified stop's end (the hold's start without one) before the speed is judged
    speed_tolerance: float  # m/s, once settled
    altitude_tolerance: float  # m from where the hold began, judged throughout
    confirm: float  # s watched after the hold began (at least until settled)
    exit_timeout: float  # s for the whole hand-over (keep it below systemd's TimeoutStopSec, 10 s)
    # m/s: the braking before the hand-over waits (at most `settle` s past the verified stop's end)
    # for the estimate's speed under this; 0: [safety] rest_speed
    rest_speed: float = 0.0
    # s past the verified stop's end before the speed is judged: the autopilot trails its setpoints
    trail: float = 0.0


# Measured on the real simulators (2026-12-02, docs/handover.md):
# PX4 SIH 1.15 (px4_1..5): under 0.3 m/s 3.5-5.8 s after SIGTERM at 3.3 m/s (the estimate),
# AUTO.LOITER's estimate drifting at up to 0.50-0.65 m/s while holding (|vz| <= 0.31 m/s), the
# estimated altitude within 0.41 m for 10 s (truth: 0.17 m, <= 0.31 m/s). ArduCopter 4.6 (ap_1..4):
# under 0.3 m/s within 2.2-2.6 s, altitude within 0.04 m, speed <= 0.19 m/s. Both catch a
# pilot-mode descent (2.5 m/s) within 0.4 s on the altitude alone.
# PX4's rest speed (2026-12-03, PX4 SIH at 9ececfdd, SIGTERM at 2.89 m/s): waiting for its estimate
# under [safety] rest_speed (0.2 m/s) ran out (its estimate strays in OFFBOARD, and in AUTO.LOITER
# at rest moves at up to 0.47-0.65 m/s), and the exit took 8.76 s of the 9.5; it is under 1 m/s
# soon after the stop's end (above). 0.7 m/s: above what PX4's estimate shows at rest; judged from
# 0.35 s after the stop's end (PX4 follows plans 0.31-0.38 s late, best fit), so that the vehicle
# itself, not only the plan, has nearly stopped when AUTO.LOITER takes over.
HOLD_PROFILES: dict[str, HoldProfile] = {
    "px4": HoldProfile(settle=2.0, speed_tolerance=1.0, altitude_tolerance=1.0, confirm=3.0, exit_timeout=9.5,
                       rest_speed=0.7, trail=0.35),
    "ardupilot": HoldProfile(settle=3.0, speed_tolerance=0.5, altitude_tolerance=0.5, confirm=3.0, exit_timeout=8.0),
}


def hold_profile(safety: SafetyConfig, autopilot: str | None) -> HoldProfile:
    """The autopilot's hold profile (ArduPilot's when the autopilot is not known), with every
    `[safety]` key that is set (non-zero) overriding its default."""
    base = HOLD_PROFILES["px4" if autopilot == "px4" else "ardupilot"]
    return HoldProfile(
        settle=safety.hold_settle or base.settle,
        speed_tolerance=safety.hold_speed_tolerance or base.speed_tolerance,
        altitude_tolerance=safety.hold_altitude_tolerance or base.altitude_tolerance,
        confirm=safety.hold_confirm or base.confirm,
        exit_timeout=safety.exit_timeout or base.exit_timeout,
        rest_speed=safety.hold_rest_speed or base.rest_speed or safety.rest_speed,
        trail=base.trail,
    )


def _unobserved(_call: int, _step: int, _rules: HoldRules, _before: HoldState, _seen: HoldObservation,
                _after: HoldState, _action: HoldAction) -> None:
    """What the hand-over shows its hold rules' calls to when nothing records."""


def in_mode(mode: str, state: Any) -> bool:
    return bool(state.mode == mode)


def at_rest(velocity: np.ndarray, threshold: float) -> bool:
    return bool(np.all(np.isfinite(velocity))) and float(np.linalg.norm(velocity)) <= threshold


class HandOver:
    def __init__(self, cfg: Config, flight: Supervisor, control: Control, link: MavlinkLink, navigator: Navigator,
                 report: Reporter, cancel_sequence: Callable[[], None]) -> None:
        self.cfg = cfg
        self.flight = flight
        self.control = control
        self.link = link
        self.nav = navigator
        self.report = report
        self.cancel_sequence = cancel_sequence  # the running command sequence (Commands owns it)
        self._settle_by: float | None = None  # loop time: the hand-over's vehicle settled by then
        self._stall_task: asyncio.Task[None] | None = None  # what a stall of the companion set off
        self._holds = itertools.count(1)  # holds watched, numbered for the recorder
        # the flight recorder's view of each call of the hold's rules
        self.observe: Callable[[int, int, HoldRules, HoldState, HoldObservation, HoldState, HoldAction],
                               None] = _unobserved

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
        pr = self.hold_profile()
        ctl, rest = self.control, pr.rest_speed  # PX4's estimate is rarely under 0.2 m/s: its own
        end = ctl.active.t_end if ctl.active is not None else 0.0
        judged_from = end + pr.trail  # the autopilot trails the stop's end by its lag
        left = max(0.0, end - (ctl.now() if ctl.flying else 0.0))
        # the autopilot's own braking trails the stop (PX4 ~0.3 s late): `settle` s are allowed
        self._settle_by = asyncio.get_running_loop().time() + left + self.hold_profile().settle
        try:
            await self.link.wait_for(
                lambda s: not ctl.flying or (ctl.now() >= judged_from and at_rest(s.velocity, rest)),
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
        rules = HoldRules(pr.altitude_tolerance, pr.speed_tolerance, pr.settle, pr.confirm)
        run = RuleRun(hold_step, rules, HoldState(), "hand-over", next(self._holds), self.observe)
        step = run.step
        action = step(Began(loop.time(), float(st.position[2]), st.mode, self._settle_by))
        while isinstance(action, Watch):
            await asyncio.sleep(action.seconds)
            v = st.velocity
            action = step(Seen(loop.time(), bool(st.armed), st.mode, float(st.position[2]),
                               (float(v[0]), float(v[1]), float(v[2]))))
        state = run.state
        mode_now, watched = state.mode, action.watched
        fields = {"mode": st.mode, "reason": reason, "altitude_change": round(state.worst_dz, 3),
                  "speed_max": round(state.worst_v, 3), "watched_s": watched,
                  "limits": {"altitude": pr.altitude_tolerance, "speed": pr.speed_tolerance,
                             "settle_s": pr.settle, "confirm_s": pr.confirm, "rest_speed": pr.rest_speed}}
        worst_dz, worst_v = state.worst_dz, state.worst_v
        if isinstance(action, Fails):
            msg = (f"{reason}: the hand-over to {mode_now} does not hold: {action.problem} (limits "
                   f"{pr.altitude_tolerance:g} m, {pr.speed_tolerance:g} m/s after {pr.settle:g} s to settle, "
                   f"over {pr.confirm:g} s; [safety] hold_* keys)")
            log.error("%s", msg)
            self.report.event("handover", msg, held=False, **fields)
            return False
        self.report.event("handover", f"{reason}: the autopilot holds the vehicle in {mode_now} ({why}): "
                          f"altitude within {abs(worst_dz):.2f} m, speed under {worst_v:.2f} m/s for "
                          f"{watched:g} s", held=True, **fields)
        return True

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
