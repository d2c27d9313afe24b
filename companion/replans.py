"""Replans of the mission in flight: a change, a pop-up obstacle, a fleet conflict.

Each replans what is left of the flown route from a split a little ahead of now (a local
replan first, then the whole remainder) and swaps it in through the one retry loop
(companion.split_swap). A pop-up races its replan against the braking deadline
(companion.braking). One owner: `Replans` (held by the navigator) owns the obstacles' updates,
whether the flown mission's durations are the user's now, and the last replan's latency.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable
from functools import partial
from typing import Any

from companion import choice_rules as cr
from companion.braking import Brakes, RaceSteps, Replanned, StopGuard, brake_deadline
from companion.config import Config
from companion.control import Control
from companion.edits import LocalEdit, Refused, resolve_planned
from companion.flight import State
from companion.mission import local_replan, replan_remainder, trim
from companion.obstacles import ObstacleStore
from companion.plan_budget import PlanBudget
from companion.race_rules import Brake, Clear, PopUp, Race
from companion.report import Reporter
from companion.route import Outcome, Route
from companion.runtime import Runtime
from companion.split_swap import SplitSwap, Swapped, logged, neighbours
from companion.supervisor import ReplanFlown, Supervisor
from companion.wire.encode import num
from companion.wire.messages import Change, ObstacleUpdate
from planner_core import AddObstacles, FloatArray, Polytope, Trajectory, first_hit

S = State


class Replans:
    def __init__(self, cfg: Config, flight: Supervisor, control: Control, runtime: Runtime, report: Reporter,
                 lock: asyncio.Lock, budget: PlanBudget, obstacles: ObstacleStore, swap: SplitSwap, brakes: Brakes,
                 fleet: Any) -> None:
        self.cfg = cfg
        self.flight = flight
        self.control = control
        self.runtime = runtime
        self.report = report
        self.lock = lock  # the navigator's: one plan change at a time
        self.budget = budget
        self.obstacles = obstacles  # written here only (on_obstacles)
        self.swap = swap
        self.brakes = brakes
        self.fleet = fleet  # companion.deconfliction.Deconfliction, or None without [fleet]
        # a change gave the flown mission times (a set duration, appended durations): from then on
        # its replans keep times, as a mission that gave durations (a new mission clears it)
        self.user_timed = False
        self.replan_latency: float | None = None

    def mission_started(self) -> None:
        """A new mission flies: its durations are the planner's again unless it gave them."""
        self.user_timed = False

    def allocates(self, r: Route) -> bool:
        """Durations the mission did not give are the planner's to choose again from the split."""
        return r.mission.durations is None and self.cfg.planner.timing == "fastest" and not self.user_timed

    def in_flight(self) -> bool:
        """A mission is flown under our control: there is something to replan."""
        return self.flight.state is S.STREAMING and self.control.route is not None and self.control.flying

    # -- changes ------------------------------------------------------------------------------------

    async def on_change(self, change: Change, arrived: float) -> None:
        if self.control.route is None or not self.flight.flying_ours or not self.control.flying:
            why = ("the mission was interrupted by a stop: send 'resume' first" if self.control.interrupted is not None
                   else f"no mission in flight ({self.flight.state.value})")
            self.report.reject("change", "", why)
            return
        async with self.lock:
            refused: list[Refused] = []
            description: list[str] = []
            timed: list[bool] = [False]

            async def plan_at(base: Trajectory, t_split: float) -> Outcome:
                assert self.control.route is not None
                r = trim(self.control.route, self.control.now())
                resolved = resolve_planned(r, change, t_split, self.allocates(r))
                if isinstance(resolved, Refused):
                    refused.append(resolved)
                    return Outcome(False, message=resolved.reason)
                description[:] = [resolved.description]
                timed[:] = [resolved.sets_times]
                remainder = (resolved.waypoints, resolved.times, resolved.labels)
                return await self._replan_outcome(r, base, t_split, resolved.local, remainder,
                                                  allocate=resolved.allocate)

            done = await self._replan_swapped(f"change ({change.key})", arrived, plan_at)
            what = description[0] if description else change.key
            if refused:
                self.report.reject("change", refused[0].field, refused[0].reason)
            elif done.ok:
                self.user_timed = self.user_timed or timed[0]
                self.report.event("accepted", f"change: {what}", key="change")
            else:
                # The current plan is still safe: a change that cannot be planned is refused.
                self.report.reject("change", "", f"change ({what}): no verified plan ({done.reason}); "
                                   "the current plan continues")

    async def _replan_outcome(self, r: Route, base: Trajectory, t_split: float, local: LocalEdit | None,
                              remainder: tuple[FloatArray, FloatArray, FloatArray] | None,
                              notes: list[str] | None = None, on_fallback: Callable[[], None] | None = None,
                              allocate: bool | None = None) -> Outcome:
        """A local replan (in this process: a few ms), then a replan of the whole remainder in
        the urgent worker (`allocate`: with durations chosen again; default: when the mission's
        durations were the planner's). Which, is companion.choice_rules' (a replan's run)."""
        messages = notes if notes is not None else []
        if allocate is None:
            allocate = self.allocates(r)
        run = self.brakes.choices.run(cr.ReplanRules(local is not None, allocate), cr.ChoiceState())
        action = run.step(cr.Ask())
        if isinstance(action, cr.Plan) and action.call == cr.LOCAL:
            assert local is not None
            out: Outcome = logged(await self.runtime.run(self.runtime.replan_pool, local_replan, r, t_split,
                                                         local, self.obstacles.known(), self.cfg,
                                                         neighbours(self.fleet, r.mission.bounds)))
            action = run.step(cr.Answer(out.ok, out.status.name, out.message))
            if isinstance(action, cr.Take):
                out.stats.setdefault("method", "local")
                return out
            messages.append(f"local replan: {out.message}")
        assert isinstance(action, cr.Plan) and action.call == cr.REMAINDER
        if on_fallback is not None:
            on_fallback()
        extra = () if remainder is None else remainder
        # The fastest-allocation search is cut to what fits before the split, as a mission's is
        # (fly): the swap refuses a plan ready after t_split - lead, and a whole search (~30
        # candidate plans, each detour tried) took 0.45-0.5 s on the loaded 2-core machine for a
        # wall across a leg: past the 0.15 s to the split, and again past the braking deadline.
        n = len(r.waypoints) + 2  # a detour's two points
        cap = self.budget.candidates_within(n, t_split - self.control.committed()) if action.allocate else None
        kw: dict[str, Any] = {"candidates": cap} if cap else {}
        out = logged(await self.runtime.plan(partial(replan_remainder, allocate=action.allocate,
                                                     neighbours=neighbours(self.fleet, r.mission.bounds), **kw),
                                             r, base, t_split, self.obstacles.known(), self.cfg, *extra, urgent=True))
        if self.cfg.planner.fallback_delay > 0:
            await asyncio.sleep(self.cfg.planner.fallback_delay)
        out.stats["method"] = "detour" if out.stats.get("detour") else "remainder"
        run.step(cr.Answer(out.ok, out.status.name, out.message))
        if not out.ok:
            messages.append(f"full replan: {out.message}")
        return out

    async def _replan_swapped(self, what: str, arrived: float, plan_at: Callable[[Trajectory, float], Awaitable[Outcome]],
                              hit: float | None = None, notes: list[str] | None = None) -> Swapped:
        """`SplitSwap.at_split` for a replan: time it, say what was swapped in."""
        t0 = time.perf_counter()
        waited = time.monotonic() - arrived
        done = await self.swap.at_split(what, arrived, plan_at, hit=hit, notes=notes)
        self.replan_latency = time.perf_counter() - t0
        if done.ok:
            assert done.outcome is not None
            stats = done.outcome.stats
            if self.flight.state is not S.STREAMING:
                self.flight.handle(ReplanFlown(what))
            self.report.event("replanned", f"{what}: {stats.get('method', 'local')} replan verified in "
                              f"{self.replan_latency * 1000:.1f} ms, split at t={done.t_split:.3f} s",
                              method=stats.get("method", "local"), split_time=round(done.t_split, 4),
                              replan_ms=round(self.replan_latency * 1000, 2),
                              compute_ms=num(float(stats.get("plan_seconds", math.nan)) * 1000, 2),
                              before_replan_ms=round(waited * 1000, 2),
                              resolved_jets=stats.get("resolved_jets"), detour=stats.get("detour"))
        return done

    # -- obstacles ----------------------------------------------------------------------------------

    async def on_obstacles(self, update: ObstacleUpdate, arrived: float) -> None:
        why = self.obstacles.refusal(update.add, update.remove, update.clear)
        if why is not None:
            self.report.reject("obstacles", "add", why, held=len(self.obstacles))
            return
        added, removed, unknown = self.obstacles.update(update.add, update.remove, update.clear)
        note = f"; unknown ids ignored: {unknown}" if unknown else ""

        def announce() -> None:
            self.report.event("accepted", f"obstacles: added {added}, removed {removed}{note}",
                              key="obstacles", added=added, removed=removed)

        if added:
            # said once the replan is under way: the event costs time a pop-up does not have
            await self.avoid([p for _, p in update.add], added, arrived, announce)
        else:
            announce()

    async def avoid(self, new: list[Polytope], ids: list[str], arrived: float, announce: Callable[[], None]) -> None:
        """What a pop-up leads to is decided by companion.race_rules (announce only, no replan,
        brake now, or race a replan against the braking deadline); this observes and carries out."""
        names = str(ids)
        race = self.brakes.race_guard
        route = self.control.route
        if race is not None and self.control.active is race.base and route is not None and self.control.flying:
            # A replan for an earlier pop-up holds the lock until it is swapped in or its
            # braking deadline: this obstacle may need the stop sooner.
            now = self.control.now()
            hit = first_hit(race.base, now, new, route.mission.radius)
            if hit is not None:
                race.bring_forward(brake_deadline(race.base, now, hit, route.mission.bounds), hit, names)
        async with self.lock:
            steps = self.brakes.race_steps(names)
            route = self.control.route
            if not self.in_flight() or route is None:
                action = steps.step(PopUp(False))
            else:
                active = self.control.active
                assert active is not None
                now = self.control.now()
                hit = first_hit(active, now, new, route.mission.radius)
                action = steps.step(PopUp(True, now, hit, self.control.committed()))
            if isinstance(action, Race):
                assert steps.state.hit is not None
                await self._avoid_race(new, names, arrived, steps.state.hit, announce, steps)
                return
            announce()
            if isinstance(action, Clear):
                self.report.event("obstacles_clear", action.event, obstacles=ids)
            elif isinstance(action, Brake):  # setpoints up to now + lead are sent: too close to replan
                await self.brakes.brake(action.reason, arrived)

    async def _avoid_race(self, new: list[Polytope], names: str, arrived: float, hit: float,
                          announce: Callable[[], None], steps: RaceSteps) -> None:
        """Race the replan against the braking deadline: the latest start of a stop that ends
        before the flown plan would enter the obstacle. A verified stop is prepared in parallel
        (at once if the deadline is near, else when the local replan fails or runs late) and
        swapped in at its start unless a verified replan was swapped in first."""
        assert self.control.route is not None and self.control.active is not None
        base, bounds, now = self.control.active, self.control.route.mission.bounds, self.control.now()
        guard = StopGuard(base, hit)
        guard.steps = steps  # the pop-up's decisions go on with the race's
        notes: list[str] = []
        edit = LocalEdit((AddObstacles(tuple(new)),), f"avoid obstacles {names}")
        what = steps.rules.what

        async def plan_at(base_now: Trajectory, t_split: float) -> Outcome:
            assert self.control.route is not None
            r = trim(self.control.route, self.control.now())
            return await self._replan_outcome(r, base_now, t_split, edit, None, notes, on_fallback=guard.prepare)

        async def replan() -> Replanned:
            done = await self._replan_swapped(what, arrived, plan_at, hit=hit, notes=notes)
            if done.ok:
                return Replanned(True)
            out = done.outcome
            if out is not None and out.blocked_waypoint is not None:
                return Replanned(False, "; ".join(notes), out.blocked_waypoint, out.message)
            return Replanned(False, "; ".join(notes) or done.reason)

        task = asyncio.create_task(replan())
        await asyncio.sleep(0)  # the replan is handed to its thread first; the rest overlaps it
        guard.bring_forward(brake_deadline(base, now, hit, bounds), hit)
        announce()
        await self.brakes.race(guard, task, notes, arrived, what)

    # -- the fleet -----------------------------------------------------------------------------------

    def fleet_replan(self, reason: str) -> None:
        """A vehicle that outranks us committed a trajectory conflicting with ours (the protocol was
        broken: a delay over [fleet] max_delay, a restart): replan what is left against it, or brake."""
        if not self.in_flight():
            self.report.event("fleet", f"deconfliction: {reason}; not flying a mission: nothing to replan")
            return
        asyncio.get_running_loop().create_task(self._fleet_replan(reason))

    async def _fleet_replan(self, reason: str) -> None:
        arrived = time.monotonic()
        async with self.lock:
            if not self.in_flight():
                return

            async def plan_at(base: Trajectory, t_split: float) -> Outcome:
                assert self.control.route is not None
                r = trim(self.control.route, self.control.now())
                return await self._replan_outcome(r, base, t_split, None, None)

            done = await self._replan_swapped(f"fleet ({reason})", arrived, plan_at)
            if not done.ok:
                await self.brakes.brake(f"deconfliction: {reason}; no separated replan ({done.reason})", arrived)
