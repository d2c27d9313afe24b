"""How well the vehicle follows its setpoints, and the lead that makes up for its lag.

Each position sample is measured against the setpoint of the measurement's own time: above
`[planner] tracking_allowance` (the margin the obstacles are inflated by) for a few samples in
a row while a plan is flown, the vehicle brakes to a verified stop and holds: decided by the pure
rules of companion/tracking_rules.py, each call shown to the flight recorder (/tracking/step) and
re-run by replay, and carried out here. The lag behind the
setpoints is estimated from the same samples (companion.lag); with `[setpoints] lead = "auto"`
the setpoints lead by it. This module is the one writer of the setpoints' lead.
"""

from __future__ import annotations

import asyncio
import collections
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.config import Config, tracking_allowance
from companion.control import Control
from companion.flight import State
from companion.lag import LagEstimator, initial_aim, initial_aim_horizontal, initial_lead
from companion.navigator import Navigator
from companion.report import Reporter
from companion.supervisor import Supervisor
from companion.tracking_rules import (
    TRACKING_MAX_SHARE,
    TRACKING_RMS_SHARE,
    TRACKING_SAMPLES,
    TRACKING_WINDOW,
    MarginEvent,
    Output,
    TrackingEvent,
    TrackingRules,
    TrackingSample,
    TrackingState,
    tracking_step,
)
from companion.wire.mavlink import MavlinkLink

S = State
LEAD_SLEW = 0.1  # s per s: how fast the auto lead follows the lag estimate (the setpoints run 10 % fast or slow)
__all__ = ["TRACKING_MAX_SHARE", "TRACKING_RMS_SHARE", "TRACKING_SAMPLES", "TRACKING_WINDOW", "StepObserver",
           "Tracking"]
log = logging.getLogger("companion")
# what an observer of the rules is shown, once per call that changed or said something: the
# state before, the reading, the state after, the outputs and the sample's time
StepObserver = Callable[[TrackingState, TrackingSample, TrackingState, tuple[Output, ...], float], None]


def _unobserved(*_call: Any) -> None:
    pass


class Tracking:
    def __init__(self, cfg: Config, flight: Supervisor, control: Control, link: MavlinkLink, navigator: Navigator,
                 report: Reporter) -> None:
        self.cfg = cfg
        self.flight = flight
        self.control = control
        self.link = link
        self.nav = navigator
        self.report = report
        # tracking: measured position against the setpoint of the measurement's time
        self.tracking_error: float | None = None
        self.tracking_error_max = 0.0  # since the service started
        # what the rules (companion.tracking_rules) remember between samples; replaced by _step only
        self.rules = TrackingRules.of(cfg)
        self.state = TrackingState()
        self._observe: StepObserver = _unobserved
        self._tracking_stop: asyncio.Task[None] | None = None  # the hold the rules asked for last
        self._allowance_said: str | None = None  # the autopilot whose default allowance was said
        self._limits: tuple[str | None, tuple[float, str, float]] | None = None  # _limit's, for the autopilot
        # lag compensation: the vehicle's lag behind the setpoints it is sent, from telemetry
        self.lag = LagEstimator(cap=cfg.setpoints.lead_max)
        self._leads: collections.deque[tuple[float, float]] = collections.deque()  # (t, lead) sampled
        self._lead_set_at: float | None = None
        self.lead_target: Any = None  # the setpoint thread (its `lead` is set here only: steer_lead)

    @property
    def lag_estimate(self) -> float | None:
        return self.lag.estimate

    def connect(self, observe: StepObserver) -> None:
        """Who is shown the calls of the rules (the recorder's tap: it must return at once)."""
        self._observe = observe

    def allowance(self) -> tuple[float, str]:
        """(the tracking allowance in use, where it comes from): `[planner] tracking_allowance`,
        or with "autopilot" the linked autopilot's (companion.config.TRACKING_ALLOWANCES)."""
        return tracking_allowance(self.cfg.planner, self.link.state.autopilot)

    def check_tracking(self, measured_at: float) -> None:
        """Each position sample: the time-aligned tracking error, judged by the pure rules
        (companion.tracking_rules.tracking_step: above the limit for TRACKING_SAMPLES samples in
        a row while a plan is flown, brake to a verified stop and hold, or say so once when
        holding already; the measured RMS or max nearing it, said once per flight phase: the
        certificate assumes the allowance holds), and the lag estimated from it."""
        st, ctl, fl = self.link.state, self.control, self.flight
        err = ctl.tracking_error(st.position, measured_at) if fl.controlling else None
        self.tracking_error = err
        ours = fl.flying_ours
        if err is None or not ours:
            self._step(self._reading(err, ours), measured_at)
            self.lag.hold()
            return
        self.tracking_error_max = max(self.tracking_error_max, err)
        self._estimate_lag(measured_at)
        self._step(self._reading(err, ours), measured_at)

    def _limit(self) -> tuple[float, str, float]:
        """(the brake's limit, its name, the allowance): they change only with the autopilot
        linked (the configuration is frozen), so they are built once for each, not each sample."""
        autopilot = self.link.state.autopilot
        cached = self._limits
        if cached is not None and cached[0] == autopilot:
            return cached[1]
        brake = self.cfg.safety.tracking_brake
        allowance, source = tracking_allowance(self.cfg.planner, autopilot)
        name = "[safety] tracking_brake" if brake else \
            "[planner] tracking_allowance" + ("" if source.startswith("[planner]") else f" ({source})")
        limit = (brake or allowance, name, allowance)
        self._limits = (autopilot, limit)
        return limit

    def _reading(self, err: float | None, ours: bool) -> TrackingSample:
        fl, stop = self.flight, self._tracking_stop
        limit, name, allowance = self._limit()
        return TrackingSample(err, ours, fl.state is S.STREAMING and fl.airborne, limit, name, allowance,
                              stop is not None and not stop.done())

    def _step(self, reading: TrackingSample, measured_at: float) -> None:
        """One call of the pure rules: the state replaced, the call shown to the observer (the
        recorder: not a call that changed nothing and said nothing, most of them on the ground),
        then the outputs carried out in order."""
        before = self.state
        self.state, outputs = tracking_step(self.rules, before, reading)
        if outputs or self.state is not before:
            try:  # shown before the hold is asked for: numbered before the transitions it causes
                self._observe(before, reading, self.state, outputs, measured_at)
            except Exception:  # a recorder's fault must never keep the vehicle from braking
                log.exception("tracking: the step observer failed")
        for out in outputs:
            if isinstance(out, MarginEvent):
                self.report.event("tracking_margin", out.message(), rms=round(out.rms, 3), max=round(out.worst, 3),
                                  limit=out.limit, limit_name=out.limit_name, tracking_allowance=out.allowance,
                                  samples=out.samples)
            elif isinstance(out, TrackingEvent):
                ref = self.control.reference(measured_at)
                self.report.event("tracking", out.message(), error=round(out.error, 3), limit=out.limit,
                                  samples=out.samples, position=[round(float(x), 3) for x in self.link.state.position],
                                  setpoint=None if ref is None else [round(float(x), 3) for x in ref])
            else:
                self._tracking_stop = asyncio.get_running_loop().create_task(self.nav.hold(out.reason, None))

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
        self._set_aim()

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
        if self.lead_target is not None and not self.control.streaming:
            self._set_aim()
        allowance, source = self.allowance()
        if source.startswith("[planner]") or self._allowance_said == self.link.state.autopilot:
            return
        self._allowance_said = self.link.state.autopilot
        self.report.event("limits", f"tracking allowance {allowance:.2f} m ({source}; [planner] tracking_allowance "
                          "sets another): obstacles are inflated by vehicle_radius + it, and a tracking error above "
                          "it brakes", tracking_allowance=allowance, tracking_allowance_from=source)

    def _set_aim(self) -> None:
        """The aim beyond the plan (`[setpoints] accel_lead`, per autopilot with "autopilot"):
        set when the sender is built and at link-up, never while streaming (it would move the
        setpoints by up to k F in one tick)."""
        sp = self.cfg.setpoints
        k, tc = initial_aim(sp.accel_lead, sp.accel_lead_tc, self.link.state.autopilot)
        self.lead_target.accel_lead, self.lead_target.accel_lead_tc = k, tc
        self.lead_target.aim_horizontal = initial_aim_horizontal(sp.aim_horizontal, self.link.state.autopilot)

    def _set_lead(self, lead: float) -> None:
        """The one writer of the setpoints' lead."""
        self.lead_target.lead = lead
