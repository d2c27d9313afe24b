"""The autopilot's limits, read at link-up and after a reconnect, and the bounds planned with.

Reading runs as a task of its own on the loop (PARAM_REQUEST_READ by name, a timeout and
retries each), so neither the loop nor the setpoint stream ever waits for it. Until it
finishes, plans use the configured bounds clipped to the autopilot's stock defaults (the
profile's), never the configured bounds alone: what the autopilot does not say is assumed
to be its default.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from dataclasses import replace

from companion.config import Config
from companion.limits import AutopilotLimits, Clip, clip_bounds, clips_text, limits_from_params
from companion.report import Reporter
from companion.wire.limits_params import names_to_read
from companion.wire.mavlink import MavlinkLink
from companion.wire.messages import MissionSpec, bounds_from
from planner_core import Bounds

log = logging.getLogger("companion")


class LimitsWatch:
    def __init__(self, cfg: Config, link: MavlinkLink, report: Reporter) -> None:
        self.cfg = cfg
        self.link = link
        self.report = report
        self.limits: AutopilotLimits | None = None  # None: not known (reading off, or no autopilot yet)
        self.reading = False
        self._task: asyncio.Task[None] | None = None
        self._defaults_said: set[str] = set()  # parameters whose defaults were said (once each)

    @property
    def headroom(self) -> float:
        return self.cfg.autopilot_limits.headroom

    def assumed(self) -> AutopilotLimits | None:
        """The limits read, or, before they are (or when the autopilot is known but not yet
        read), the autopilot's stock defaults: never none at all for a known autopilot."""
        if self.limits is not None or not self.cfg.autopilot_limits.read:
            return self.limits
        ap = self.link.state.autopilot
        return None if ap is None else limits_from_params(ap, {})

    def clip(self, bounds: Bounds) -> tuple[Bounds, list[Clip]]:
        return clip_bounds(bounds, self.assumed(), self.headroom)

    def default_bounds(self) -> Bounds:
        """The configured bounds, clipped to the autopilot's limits x headroom."""
        return self.clip(bounds_from(None, self.cfg))[0]

    def mission(self, spec: MissionSpec) -> tuple[MissionSpec, list[Clip]]:
        """`spec` with its bounds clipped to the autopilot's limits (and the clips)."""
        bounds, clips = self.clip(spec.bounds)
        return (replace(spec, bounds=bounds), clips) if clips else (spec, [])

    # -- reading ------------------------------------------------------------------------

    def read(self, why: str) -> None:
        """Read the limits again (link-up, reconnect): a task; the previous read is dropped."""
        if not self.cfg.autopilot_limits.read:
            return
        if self._task is not None and not self._task.done():
            self._task.cancel()
        with contextlib.suppress(RuntimeError):  # no running loop (unit tests)
            self._task = asyncio.get_running_loop().create_task(self._read(why))

    async def _read(self, why: str) -> None:
        ap = self.link.state.autopilot
        if ap is None:
            return
        names = names_to_read(ap)
        al = self.cfg.autopilot_limits
        self.reading = True
        try:
            answered = await self.link.read_params(names, al.timeout, al.retries)
        except OSError as exc:
            log.warning("autopilot limits not read: %s", exc)
            answered = {}
        finally:
            self.reading = False
        lim = limits_from_params(ap, answered)
        if lim is None:
            return
        self.limits = lim
        defaulted = [n for n in lim.defaulted() if n not in self._defaults_said]
        if defaulted:
            self._defaults_said.update(defaulted)
            tries = al.retries + 1
            self.report.event("limits", f"the autopilot did not answer for {', '.join(defaulted)} ({tries} request(s), "
                              f"{al.timeout:g} s each): planning with its stock defaults for them",
                              defaulted=defaulted, autopilot=ap)
        clips = self.clip(bounds_from(None, self.cfg))[1]
        got = ", ".join(f"{k} {v.value:.3g}" for k, v in lim.fields().items() if v.source == "param")
        text = (f"autopilot limits read ({why}): {got or 'none answered'}; headroom {self.headroom:g}; "
                + (f"configured bounds clipped: {clips_text(clips)}" if clips else "configured bounds within them"))
        self.report.event("limits", text, limits=lim.as_status(), headroom=self.headroom,
                          clipped=[c.as_dict() for c in clips], why=why)
        log.info("%s", text)
