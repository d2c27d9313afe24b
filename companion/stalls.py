"""The companion's own stalls: setpoints that stop leaving while streaming, and an event
loop or setpoint thread that did not run for `[setpoints] loop_stall_limit`.

Either is said (status `setpoints_stalled`, `error` and `stalled` events, with the cause: the
companion, not the link) and dealt with before setpoints leave again (companion.handover).
A hung loop is systemd's watchdog's: it is fed only from setpoint ticks handled on the loop.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from companion.config import Config
from companion.control import Control
from companion.handover import HandOver
from companion.report import Reporter
from companion.rule_run import RuleRun
from companion.sendproc import SetpointProcess
from companion.setpoints import Liveness, SetpointSender
from companion.stall_rules import (
    Action,
    Beat,
    Observation,
    Quiet,
    Settled,
    Stalled,
    StallRules,
    StallState,
    stall_step,
)
from companion.supervisor import Supervisor
from companion.wire import encode as enc
from companion.wire.mavlink import MavlinkLink


def _unobserved(_rules: StallRules, _before: StallState, _seen: Observation, _after: StallState,
                _action: Action) -> None:
    """What the watch shows its rules' calls to when nothing records."""


class StallWatch:
    def __init__(self, cfg: Config, stop: asyncio.Event, report: Reporter, link: MavlinkLink, control: Control,
                 flight: Supervisor, sender: SetpointSender | SetpointProcess, handover: HandOver) -> None:
        self.cfg = cfg
        self.stop = stop  # the service's loops end
        self.report = report
        self.link = link
        self.control = control
        self.flight = flight
        self.sender = sender
        self.handover = handover
        # the loop's beat, which the setpoint thread checks before each send
        self.liveness = Liveness(cfg.setpoints.loop_stall_limit)
        self.setpoints_stalled = False
        # the flight recorder's view of each call of the stall rules that changed or did something
        self.observe: Callable[[StallRules, StallState, Observation, StallState, Action], None] = _unobserved

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

    def stalled(self) -> bool:
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
        rules = StallRules(self.cfg.setpoints.loop_stall_limit)
        live = self.liveness

        def shown(before: StallState, seen: Observation, after: StallState, action: Action) -> bool:
            # a quiet beat that changes nothing is not shown (50 a second); the rest is rare
            return after != before or not isinstance(action, Quiet) or isinstance(seen, Settled)

        step = RuleRun(stall_step, rules, StallState(), "stalls", 0,
                       lambda _n, _k, r, b, o, a, act: self.observe(r, b, o, a, act), shown).step

        live.beat()
        step(Settled(self.flight.state.value))
        while not self.stop.is_set():
            await asyncio.sleep(period)
            gap = live.beat()
            withheld = live.withheld
            now = time.monotonic()
            action = step(Beat(gap, None if withheld is None else withheld[1],
                               0.0 if withheld is None else withheld[2], now - live.last_sent,
                               self.flight.controlling, self.flight.state.value))
            if isinstance(action, Stalled):
                self._stalled(action)
                step(Settled(self.flight.state.value))

    def _stalled(self, stall: Stalled) -> None:
        """Carry out what the rules decided about a stall, then say it."""
        if stall.reaction == "release":
            self.handover.after_stall(stall.reason)
            reaction = "released control"
        elif stall.reaction == "hold":
            reaction = self.handover.hold_after_stall(stall.reason)
        else:
            reaction = "not in control"
        self.liveness.release()
        link = self.link.link_ok()
        silent = (f"setpoints were withheld for {stall.silence * 1000:.0f} ms" if stall.withheld
                  else "no setpoint was withheld")
        self.report.event(
            "stalled", f"{stall.reason} while {stall.was}: cause the companion, not the link (the autopilot "
            f"{'is heard' if link else 'is not heard either'}); {silent}; {reaction}; now "
            f"{self.flight.state.value}, mode {self.link.state.mode}",
            cause="companion", stalled=stall.what.removeprefix("its ").replace(" ", "_"),
            stall_ms=round(stall.stall * 1000, 1), setpoints_withheld=stall.withheld,
            silence_ms=enc.ms(stall.silence, 1) if stall.withheld else None,
            previous_state=stall.was, link=link, mode=self.link.state.mode)
