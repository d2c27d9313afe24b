"""A mission accepted and started: checked and loaded, or planned from the flown state and
flown at once; and the anytime start's second step, the search for the fastest durations
swapped in later (`improve`).

One owner: `MissionStart` (held by the navigator) owns how long a mission's plan took and the
anytime search under way; what is flown stays `Control`'s, changed only through the one retry
loop (companion.split_swap).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from typing import Any

import numpy as np

from companion import choice_rules as cr
from companion.braking import ChoiceRuns, choice_runs
from companion.config import Config
from companion.control import Control, jet_on
from companion.limits import clips_text, refusal_note
from companion.mission import check_mission, replan_remainder, start_mission, start_separated
from companion.obstacles import ObstacleStore
from companion.plan_budget import FULL_SEARCH, PlanBudget, ahead_within
from companion.replans import Replans
from companion.report import Reporter
from companion.route import Outcome, OutcomeStatus, Route
from companion.runtime import Runtime
from companion.split_swap import SplitSwap, fleet_on, logged, neighbours
from companion.supervisor import MissionStarted, Supervisor
from companion.wire.encode import num
from companion.wire.messages import MissionSpec, bounds_from
from planner_core import Bounds, FloatArray, Trajectory, rest_jet

log = logging.getLogger("companion")

IMPROVE_MIN = 0.05  # s: the search's plan replaces the anytime start's only if it lands this much earlier
# s: when nothing plans from a moving split, the start is tried this much further along the flown
# plan, twice (companion.choice_rules.StartRules.later)
LATER_START = 0.25


class MissionStart:
    def __init__(self, cfg: Config, flight: Supervisor, control: Control, runtime: Runtime, report: Reporter,
                 position: Callable[[], FloatArray], lock: asyncio.Lock, budget: PlanBudget, obstacles: ObstacleStore, swap: SplitSwap,
                 replans: Replans, limits: Any, fleet: Any, choices: ChoiceRuns | None = None) -> None:
        self.cfg = cfg
        self.flight = flight
        self.control = control
        self.runtime = runtime
        self.report = report
        self.position = position  # the measured position (NED)
        self.lock = lock  # the navigator's: one plan change at a time
        self.budget = budget
        self.obstacles = obstacles
        self.swap = swap
        self.replans = replans  # the flown mission's replans: told when a new mission flies
        self.limits = limits  # companion.limits_watch.LimitsWatch, or None: the bounds flown
        self.fleet = fleet  # companion.deconfliction.Deconfliction, or None without [fleet]
        self.plan_latency: float | None = None
        self.improving: asyncio.Task[None] | None = None  # the anytime start's search (improve)
        self.choices = choices if choices is not None else choice_runs()  # which plan a start asks for

    # -- bounds within the autopilot's limits ---------------------------------------------------

    def clipped_note(self, spec: MissionSpec) -> str:
        """What the autopilot's limits lowered of the mission's bounds as given (its own, or
        the configured ones), for a refusal's reason ("" when nothing)."""
        if self.limits is None:
            return ""
        try:
            given = bounds_from(spec.raw.get("bounds"), self.cfg)
        except Exception:  # checked when the message was read; never fail a refusal on it
            return ""
        return refusal_note(self.limits.clip(given)[1], self.limits.headroom)

    def within_limits(self, spec: MissionSpec, tell: bool) -> tuple[MissionSpec, str]:
        """`spec` with its bounds clipped to the autopilot's limits x headroom; `tell`: say so
        when a mission's own bounds were clipped (the configured ones are said at link-up).
        Also returns what was clipped, for a refusal's reason."""
        if self.limits is None:
            return spec, ""
        clipped, clips = self.limits.mission(spec)
        if not clips:
            return spec, ""
        text = clips_text(clips)
        if tell and "bounds" in spec.raw:
            self.report.event("limits", f"mission {spec.id}: its bounds clipped to the autopilot's limits x headroom "
                              f"{self.limits.headroom:g}: {text}", key="mission", mission=spec.id,
                              clipped=[c.as_dict() for c in clips])
        return clipped, text

    def fleet_note(self) -> str:
        """What a refusal in a fleet adds: the vehicles planned against."""
        if not fleet_on(self.fleet):
            return ""
        names = self.fleet.names()
        return (f" (no plan keeps [fleet] separation {self.cfg.fleet.separation:g} m from "
                f"{', '.join(names)})" if names else "")

    def ahead_within(self, bounds: Bounds, ahead: float) -> float:
        """`ahead`, or further, to where the flown plan is back within `bounds` (plan_budget.ahead_within)."""
        active = self.control.active
        return ahead if active is None else ahead_within(active, self.control.committed(), bounds, ahead)

    # -- accepted: loaded, or flown at once -----------------------------------------------------

    async def on_mission(self, spec: MissionSpec, arrived: float) -> None:
        spec, _ = self.within_limits(spec, tell=True)
        if self.flight.flying_ours and spec.autostart:
            await self.fly(spec, arrived)
            return
        plan_ms = None
        pos = self.position()
        if np.all(np.isfinite(pos)):
            t0 = time.perf_counter()
            # The check only needs the verdict: a 1000-waypoint route coming back would be
            # unpickled here in one GIL-holding call of many milliseconds.
            outcome = logged(await self.runtime.plan(check_mission, replace(spec, raw={}), rest_jet(pos), 0.0,
                                                     self.obstacles.known(), self.cfg))
            plan_ms = round((time.perf_counter() - t0) * 1000, 2)
            if not outcome.ok:
                self.reject_outcome(spec, outcome)
                return
        self.control.load(spec)
        where = "on the ground" if not self.flight.airborne else f"in {self.flight.state.value}"
        self.report.event("accepted", f"mission {spec.id} loaded ({len(spec.waypoints)} waypoints, vehicle {where}); "
                          "send 'start' to fly it", key="mission", mission=spec.id, plan_ms=plan_ms, pending=True)

    def reject_outcome(self, spec: MissionSpec, outcome: Outcome) -> None:
        field = "" if outcome.blocked_waypoint is None else f"waypoints[{outcome.blocked_waypoint - spec.first_index}]"
        field = outcome.field or field
        why = outcome.message
        if outcome.status is OutcomeStatus.INFEASIBLE:  # not a mismatch, which no bound would fix
            why += self.clipped_note(spec)
        self.report.reject("mission", field, f"mission {spec.id}: {why}", mission=spec.id)

    async def fly(self, spec: MissionSpec, arrived: float | None) -> bool:
        """Plan `spec` from the flown state a little ahead of now and fly it."""
        given = spec
        spec, _ = self.within_limits(spec, tell=False)  # limits read since it was loaded
        fleet = self.fleet if fleet_on(self.fleet) else None
        async with self.lock:
            n = len(spec.waypoints)

            # the anytime start: the default allocation at once, the search's plan later (improve);
            # which plan is asked for is companion.choice_rules' (a start's run)
            rules = cr.StartRules(self.cfg.planner.anytime, self.cfg.planner.timing, spec.durations is not None,
                                  fleet is not None, LATER_START)
            run = self.choices.run(rules, cr.ChoiceState())

            async def plan_at(base: Trajectory, t_split: float) -> Outcome:
                jet = self.control.jet(t_split)
                t0 = time.perf_counter()
                # the search is cut to what fits before the split (planner_core.fastest_durations:
                # a count, so a recording replays the same plan)
                # the swap takes a plan ready before t_split - lead: the time after what is committed
                left = t_split - self.control.committed() - (fleet.wait if fleet is not None else 0.0)
                cap = self.budget.candidates_within(n, left)
                # without a fleet the call is start_mission's own (what a recording names and replays)
                search: Any = partial(start_mission, candidates=cap) if cap else start_mission
                action = run.step(cr.Ask(moving=bool(np.any(jet[1:] != 0.0))))
                while True:
                    assert isinstance(action, cr.Plan)
                    fn: Any = (partial(start_separated, neighbours=neighbours(fleet, spec.bounds), candidates=cap)
                               if action.call == cr.SEPARATED else partial(start_mission, quick=True) if action.quick
                               else search)
                    # a later start: the plan begins on the flown one, which flies on until then
                    # (the swap at t_split splices it there: the same curve up to it)
                    at = t_split + action.later
                    t1 = time.perf_counter()
                    out: Outcome = logged(await self.runtime.plan(fn, replace(spec, raw={}),
                                                                  jet_on(base, at) if action.later else jet,
                                                                  at, self.obstacles.known(), self.cfg))
                    self.budget.measured(time.perf_counter() - t1, n, int(out.stats.get("candidates", 1)))
                    action = run.step(cr.Answer(out.ok, out.status.name, out.message))
                    if isinstance(action, cr.Take):
                        break
                self.plan_latency = time.perf_counter() - t0
                return out

            ahead = self.budget.split_ahead_for(n) if cr.quick_start(rules) else self.budget.mission_ahead(n)
            done = await self.swap.at_split(f"mission {spec.id}", arrived, plan_at,
                                            ahead=self.ahead_within(spec.bounds, ahead))
            if not done.ok:
                if done.outcome is not None:
                    why = done.outcome.message
                    if fleet is not None:
                        why = fleet.named(why) + self.fleet_note()
                    self.reject_outcome(spec, replace(done.outcome, message=why))
                else:
                    self.report.reject("mission", "", f"mission {spec.id}: {done.reason}", mission=spec.id)
                return False
            assert done.outcome is not None and done.outcome.route is not None
            self.replans.mission_started()
            self.control.unload(given)
            self.flight.handle(MissionStarted(spec.id))
            lat = self.plan_latency or 0.0
            delay = done.outcome.stats.get("fleet_delay")
            waits = f"; starts {delay:g} s later to keep the separation from the other vehicles" if delay else ""
            if done.outcome.stats.get("capped"):
                waits += (f"; the search for the fastest durations stopped after {done.outcome.stats['candidates']} "
                          f"candidate plans, what fits in [planner] search_time {self.cfg.planner.search_time:g} s "
                          "at the planning speed measured here (it may fly a little slower than a full search)")
            quick = bool(run.state.quick)
            if quick:
                waits += "; flying the default durations while the fastest are searched for (event `improved`)"
            self.report.event("accepted", f"mission {spec.id}: planned and verified in {lat * 1000:.1f} ms "
                              f"({len(spec.waypoints)} waypoints, {done.outcome.route.t_end - done.t_split:.2f} s)"
                              + waits, key="mission", mission=spec.id, plan_ms=round(lat * 1000, 2),
                              compute_ms=num(float(done.outcome.stats.get("plan_seconds", math.nan)) * 1000, 2),
                              **({"fleet_delay": delay} if delay else {}))
            if quick:
                self.improving = asyncio.get_running_loop().create_task(self.improve(done.outcome.route))
            return True

    # -- the anytime start's second step ---------------------------------------------------------

    async def improve(self, quick: Route) -> None:
        """The anytime start's second step: the search for the fastest durations of what is left of
        the route flown at once on the default allocation, from a split as far ahead as the search
        takes here, swapped in if it lands earlier. Planned without the lock (a pop-up or a new
        mission must not wait for it); it gives way to anything that changed the flown plan or
        holds the lock meanwhile (the check and the swap run without yielding)."""
        n = len(quick.waypoints)
        what = f"mission {quick.mission.id}"
        # a search of about [planner] search_time here, split as far ahead as it takes
        cap = self.budget.search_cap(n)

        def superseded() -> bool:
            return self.control.route is not quick or self.lock.locked() or not self.flight.flying_ours

        # whether to search, and whether its plan replaces the quick one: companion.choice_rules'
        rules = cr.ImproveRules(quick.t_end, IMPROVE_MIN)

        async def plan_at(base: Trajectory, t_split: float) -> Outcome:
            run = self.choices.run(rules, cr.ChoiceState())
            action = run.step(cr.Ask(not superseded()))
            if isinstance(action, cr.Take):
                return Outcome(False, message=action.detail)
            t0 = time.perf_counter()
            fn: Any = (partial(replan_remainder, allocate=True, candidates=cap) if cap < FULL_SEARCH
                       else partial(replan_remainder, allocate=True))
            out: Outcome = logged(await self.runtime.plan(fn, quick, base, t_split, self.obstacles.known(), self.cfg))
            self.budget.measured(time.perf_counter() - t0, n, int(out.stats.get("candidates", 1)))
            t_end = out.route.t_end if out.route is not None else 0.0
            action = run.step(cr.Answer(out.ok, out.status.name, out.message, not superseded(), t_end))
            assert isinstance(action, cr.Take)
            if action.detail == cr.NO_EARLIER:
                return Outcome(False, message=f"the search's plan lands no earlier ({t_end - t_split:.2f} s "
                               f"against {quick.t_end - t_split:.2f} s from the split)")
            return Outcome(False, message=action.detail) if action.detail else out

        t0 = time.perf_counter()
        done = await self.swap.at_split(f"{what} (fastest durations)", None, plan_at,
                                        ahead=self.budget.split_ahead_for(n, cap))
        if not done.ok or done.outcome is None or done.outcome.route is None:
            log.info("%s: the default durations fly on: %s", what, done.reason)
            return
        stats = done.outcome.stats
        self.report.event("improved", f"{what}: the fastest durations swapped in at t={done.t_split:.3f} s, planned "
                          f"in {(time.perf_counter() - t0) * 1000:.1f} ms: lands {quick.t_end - done.outcome.route.t_end:.2f} s "
                          f"earlier ({stats.get('candidates', 1)} candidate plans"
                          + (", the search cut to what fits before the split)" if stats.get("capped") else ")"),
                          mission=quick.mission.id, split_time=round(done.t_split, 4),
                          earlier_s=round(quick.t_end - done.outcome.route.t_end, 3))
