"""The companion's own stalls: setpoints that stop leaving while streaming, and an event
loop or setpoint thread that did not run for `[setpoints] loop_stall_limit`.

Either is said (status `setpoints_stalled`, `error` and `stalled` events, with the cause: the
companion, not the link) and dealt with before setpoints leave again (companion.handover).
A hung loop is systemd's watchdog's: it is fed only from setpoint ticks handled on the loop.
"""

from __future__ import annotations

import asyncio
import time

from companion.config import Config
from companion.control import Control
from companion.handover import HandOver
from companion.report import Reporter
from companion.sendproc import SetpointProcess
from companion.setpoints import Liveness, SetpointSender
from companion.supervisor import Supervisor
from companion.wire import encode as enc
from companion.wire.mavlink import MavlinkLink

# s: setpoints withheld after a stall for less than this (half PX4's default COM_OF_LOSS_T):
# the autopilot still flies our plan, so the companion keeps control and holds
STALL_HOLD_WITHIN = 0.5


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
