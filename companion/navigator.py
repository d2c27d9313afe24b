"""Missions in flight, on the loop: load, fly, change, avoid pop-ups, stop, resume.

Which mission is flown (`route`), loaded (`pending`) or interrupted (`interrupted`) is held by
`Control`, the one owner of what is flown, and changed only with the trajectory (read here).
Planning runs in workers (companion.mission, pure); every new plan is swapped in through
`Control.swap` at a split a little ahead of now, by the one retry loop (companion.split_swap).
The navigator holds the parts, each the one owner of its state: a mission accepted, started and
improved (companion.mission_start), its replans for changes, pop-ups and the fleet
(companion.replans), the stops (companion.braking) and how long plans take
(companion.plan_budget); it answers stop, hold and resume itself.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.braking import Brakes, StopContext, choice_runs
from companion.config import Config
from companion.control import Control
from companion.flight import State
from companion.mission_start import MissionStart
from companion.obstacles import Known, ObstacleStore
from companion.plan_budget import PlanBudget
from companion.replans import Replans
from companion.report import Reporter
from companion.route import Route
from companion.runtime import Runtime
from companion.split_swap import SplitSwap, neighbours
from companion.supervisor import MissionComplete, StoppedAfterBraking, Supervisor
from companion.wire.encode import num
from companion.wire.messages import Change, MissionSpec, ObstacleUpdate, bounds_from
from planner_core import Bounds, FloatArray, segment_at

S = State


class Navigator:
    def __init__(self, cfg: Config, flight: Supervisor, control: Control, runtime: Runtime, report: Reporter,
                 position: Callable[[], FloatArray], limits: Any = None, fleet: Any = None) -> None:
        self.cfg = cfg
        self.flight = flight
        self.control = control
        self.runtime = runtime
        self.report = report
        self.position = position  # the measured position (NED)
        self.obstacles = ObstacleStore(cfg.limits.max_obstacles_held)
        self.lock = asyncio.Lock()  # one plan change at a time
        self.budget = PlanBudget(cfg)  # how long plans take here, so how far ahead they split
        # which plan each start, replan and stop asks for (companion.choice_rules), numbered as one
        self.choices = choice_runs()
        self.brakes = Brakes(cfg, flight, control, runtime, report, self.stop_context, position, self.choices)
        self.limits = limits  # companion.limits_watch.LimitsWatch (None: not read): bounds flown
        # companion.deconfliction.Deconfliction: the other vehicles' trajectories and the commit
        # protocol; None or disabled without [fleet] separation
        self.fleet = fleet
        self.split = SplitSwap(cfg, flight, control, report, fleet)  # every plan made in flight swapped in
        self.replans = Replans(cfg, flight, control, runtime, report, self.lock, self.budget, self.obstacles,
                               self.split, self.brakes, fleet)
        self.missions = MissionStart(cfg, flight, control, runtime, report, position, self.lock, self.budget,
                                     self.obstacles, self.split, self.replans, limits, fleet, self.choices)

    # -- the missions, as Control holds them (read-only here) ------------------------------

    @property
    def route(self) -> Route | None:
        """The mission being flown (its plan is in control)."""
        return self.control.route

    @property
    def pending(self) -> MissionSpec | None:
        """Loaded (or what a release left): waits for `start`."""
        return self.control.pending

    @property
    def interrupted(self) -> MissionSpec | None:
        """What a stop left of the mission: waits for `resume`."""
        return self.control.interrupted

    # -- what is known --------------------------------------------------------------------

    def known(self) -> Known:
        """Every obstacle sent on the `obstacles` key (the planners add the mission's own)."""
        return self.obstacles.known()

    def stop_context(self) -> StopContext:
        mission = self.route.mission if self.route is not None else None
        every = self.known() + (Known.of(mission.obstacles) if mission is not None else Known())
        # without a mission flown (a stop or an abort ended it) the trajectory still flies
        # within its mission's bounds, beyond the configured ones maybe: a stop from there is
        # verified within them (within the configured ones it may not exist: a hold at speed)
        flown = self.control.flown_bounds
        bounds = mission.bounds if mission is not None else flown if flown is not None else self.default_bounds()
        # in a fleet the stop (and the hold at its end) is chosen separated from the others
        nb = neighbours(self.fleet, bounds)
        names = tuple(self.fleet.order) if nb is not None else ()
        return StopContext(mission, every.polytopes, bounds, nb, names)

    def default_bounds(self) -> Bounds:
        """The configured bounds, within the autopilot's limits when they are known."""
        return bounds_from(None, self.cfg) if self.limits is None else self.limits.default_bounds()

    def has_mission(self) -> bool:
        """A mission `start`/`resume` can fly: loaded, interrupted, or still being flown."""
        if self.pending is not None or self.interrupted is not None:
            return True
        return self.route is not None and self.control.flying and self.route.t_end > self.control.now()

    def mission_id(self) -> str | None:
        for m in (self.route.mission if self.route else None, self.interrupted):
            if m is not None:
                return m.id
        return None

    # -- progress -----------------------------------------------------------------------------

    def progress(self, t: float) -> None:
        """The setpoint thread flew trajectory time t of the current plan."""
        st = self.flight.state
        if st is S.STREAMING and self.route is not None and t >= self.route.t_end:
            mid = self.route.mission.id
            self.flight.handle(MissionComplete(mid))
            self.report.event("mission_complete", f"mission {mid} complete", mission=mid)
        elif st is S.BRAKING and self.control.active is not None and t >= self.control.active.t_end:
            self.flight.handle(StoppedAfterBraking())

    def status_fields(self) -> dict[str, Any]:
        seg = progress = time_to_go = None
        r = self.route
        if r is not None and self.control.flying:
            t = self.control.now()
            i = segment_at(r.times, t)
            nxt = r.labels[i + 1 :]
            ahead = nxt[nxt >= 0]
            seg = int(ahead[0]) - 1 if len(ahead) else int(np.max(r.labels))
            progress = float(np.clip((t - r.times[0]) / max(r.t_end - r.times[0], 1e-9), 0.0, 1.0))
            time_to_go = max(r.t_end - t, 0.0)
        return {
            "mission": self.mission_id(),
            "pending_mission": None if self.pending is None else self.pending.id,
            "interrupted": self.interrupted is not None,
            "segment": seg,
            "progress": num(progress),
            "time_to_go": num(time_to_go, 3),
            "plan_latency_ms": num(None if self.missions.plan_latency is None
                                   else self.missions.plan_latency * 1000, 2),
            "replan_latency_ms": num(None if self.replans.replan_latency is None
                                     else self.replans.replan_latency * 1000, 2),
            "obstacles": self.obstacles.ids(),
        }

    # -- stop, hold, resume ---------------------------------------------------------------------

    async def resume(self, arrived: float) -> None:
        spec = self.interrupted
        if spec is None:
            if self.route is not None and self.flight.state is S.STREAMING:
                self.report.refuse("resume", f"mission {self.route.mission.id} is being flown", by="companion")
            else:
                self.report.refuse("resume", "no interrupted mission to resume (it is complete, or was aborted)",
                                    by="companion")
            return
        if await self.fly(spec, arrived):
            self.report.event("resumed", f"mission {spec.id} resumed at mission waypoint {spec.first_index}",
                              mission=spec.id, waypoint=spec.first_index)

    async def hold(self, reason: str, arrived: float | None) -> None:
        async with self.lock:
            await self.brakes.brake(reason, arrived)

    async def abort(self, arrived: float | None) -> None:
        self.control.forget()
        async with self.lock:
            if self.flight.flying_ours or (self.flight.state is S.TAKEOFF and self.control.streaming):
                await self.brakes.brake("abort command", arrived)

    def fleet_stop(self, reason: str) -> None:
        """Our clock is off the fleet's (companion.clocks): the mission flying, planned against the
        others' times, is stopped (a verified stop; a hold does not depend on the clock)."""
        if self.flight.state is S.STREAMING and self.control.flying:
            asyncio.get_running_loop().create_task(self.hold(f"fleet: {reason}", time.monotonic()))

    # -- what the parts do ------------------------------------------------------------------------

    async def on_mission(self, spec: MissionSpec, arrived: float) -> None:
        await self.missions.on_mission(spec, arrived)

    async def fly(self, spec: MissionSpec, arrived: float | None) -> bool:
        """Plan `spec` from the flown state a little ahead of now and fly it."""
        return await self.missions.fly(spec, arrived)

    async def on_change(self, change: Change, arrived: float) -> None:
        await self.replans.on_change(change, arrived)

    async def on_obstacles(self, update: ObstacleUpdate, arrived: float) -> None:
        await self.replans.on_obstacles(update, arrived)

    def fleet_replan(self, reason: str) -> None:
        self.replans.fleet_replan(reason)
