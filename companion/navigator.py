"""Missions in flight, on the loop: load, fly, change, avoid pop-ups, stop, resume.

Which mission is flown (`route`), loaded (`pending`) or interrupted (`interrupted`) is held by
`Control`, the one owner of what is flown, and changed only with the trajectory (read here).
Planning runs in workers (companion.mission, pure); every new plan is swapped in through
`Control.swap` at a split a little ahead of now, by the one retry loop `_swap_at_split`.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np

from companion.braking import Brakes, Replanned, StopContext, StopGuard, brake_deadline
from companion.config import Config
from companion.control import SWAP_LATE, Control
from companion.edits import LocalEdit, Refused, resolve_planned
from companion.flight import State
from companion.limits import clips_text, refusal_note
from companion.mission import (
    check_mission,
    local_replan,
    replan_remainder,
    start_mission,
    start_separated,
    trim,
)
from companion.obstacles import Known, ObstacleStore
from companion.plan_budget import (
    FULL_SEARCH,
    MAX_AHEAD,
    RETRY_MARGIN,
    PlanBudget,
    ahead_within,
)
from companion.report import Reporter
from companion.route import Outcome, OutcomeStatus, Route
from companion.runtime import Runtime
from companion.supervisor import (
    MissionComplete,
    MissionStarted,
    ReplanFlown,
    StoppedAfterBraking,
    Supervisor,
)
from companion.wire.encode import num
from companion.wire.messages import Change, MissionSpec, ObstacleUpdate, bounds_from
from planner_core import (
    AddObstacles,
    Bounds,
    FloatArray,
    Polytope,
    Trajectory,
    first_hit,
    rest_jet,
    splice,
)

log = logging.getLogger("companion")
S = State

IMPROVE_MIN = 0.05  # s: the search's plan replaces the anytime start's only if it lands this much earlier
FLEET_TRIES = 8  # candidates that lost to other vehicles before a plan is given up (docs/fleet.md)


@dataclass(frozen=True)
class Swapped:
    """The end of `_swap_at_split`: a plan swapped in (outcome, split time), or why not."""

    outcome: Outcome | None
    t_split: float = math.nan
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.outcome is not None and self.outcome.ok


class Navigator:
    def __init__(self, cfg: Config, flight: Supervisor, control: Control, runtime: Runtime, report: Reporter,
                 position: Callable[[], FloatArray]) -> None:
        self.cfg = cfg
        self.flight = flight
        self.control = control
        self.runtime = runtime
        self.report = report
        self.position = position  # the measured position (NED)
        self.obstacles = ObstacleStore(cfg.limits.max_obstacles_held)
        # a change gave the flown mission times (a set duration, appended durations): from then on
        # its replans keep times, as a mission that gave durations (a new mission clears it)
        self.user_timed = False
        self.lock = asyncio.Lock()  # one plan change at a time
        self.plan_latency: float | None = None
        self._improving: asyncio.Task[None] | None = None  # the anytime start's search (improve)
        self.replan_latency: float | None = None
        self.budget = PlanBudget(cfg)  # how long plans take here, so how far ahead they split
        self.brakes = Brakes(cfg, flight, control, runtime, report, self.stop_context, position)
        self.limits: Any = None  # companion.limits_watch.LimitsWatch (set by the service): bounds flown
        # companion.deconfliction.Deconfliction (set by the service): the other vehicles' trajectories
        # and the commit protocol; None or disabled without [fleet] separation
        self.fleet: Any = None

    def fleet_on(self) -> bool:
        return self.fleet is not None and bool(self.fleet.enabled)

    def neighbours(self, bounds: Bounds) -> Any:
        """The other vehicles' live trajectories for a plan in flight (None without a fleet)."""
        return self.fleet.neighbours(bounds) if self.fleet_on() else None

    def fleet_note(self) -> str:
        """What a refusal in a fleet adds: the vehicles planned against."""
        if not self.fleet_on():
            return ""
        names = self.fleet.names()
        return (f" (no plan keeps [fleet] separation {self.cfg.fleet.separation:g} m from "
                f"{', '.join(names)})" if names else "")

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
        bounds = mission.bounds if mission is not None else self.default_bounds()
        # in a fleet the stop (and the hold at its end) is chosen separated from the others
        nb = self.neighbours(bounds)
        names = tuple(self.fleet.order) if nb is not None else ()
        return StopContext(mission, every.polytopes, bounds, nb, names)

    def default_bounds(self) -> Bounds:
        """The configured bounds, within the autopilot's limits when they are known."""
        return bounds_from(None, self.cfg) if self.limits is None else self.limits.default_bounds()

    def _clipped_note(self, spec: MissionSpec) -> str:
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
            i = int(np.clip(np.searchsorted(r.times, t, side="right") - 1, 0, len(r.times) - 2))
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
            "plan_latency_ms": num(None if self.plan_latency is None else self.plan_latency * 1000, 2),
            "replan_latency_ms": num(None if self.replan_latency is None else self.replan_latency * 1000, 2),
            "obstacles": self.obstacles.ids(),
        }

    # -- the one retry loop -------------------------------------------------------------------

    async def _swap_at_split(self, what: str, arrived: float | None,
                             plan_at: Callable[[Trajectory, float], Awaitable[Outcome]],
                             hit: float | None = None, notes: list[str] | None = None,
                             ahead: float | None = None) -> Swapped:
        """Plan from a split `ahead` of now (default [planner] split_ahead) and swap the plan in.
        A plan that came after its split is planned again once, further ahead (from the time it
        took); a flown plan that changed while planning, once more. Each cause is said once, in
        its own words; the reason of a failure is the last cause. `plan_at(base, t_split)`."""
        messages = notes if notes is not None else []

        def say(text: str) -> None:
            if text not in messages:
                messages.append(text)

        ahead = self.cfg.planner.split_ahead if ahead is None else ahead
        if self.fleet_on():  # a plan is proposed, then committed 2 x max_delay later (companion.commit)
            ahead += self.fleet.wait
        late = changed = lost = 0
        reason = ""
        while late < 2 and changed < 2:
            if not self.control.flying or not self.flight.flying_ours:
                return Swapped(None, reason=f"no longer in control ({self.flight.state.value})")
            base, route = self.control.active, self.control.route
            assert base is not None
            t_split = self.control.committed() + ahead  # setpoints up to now + lead are sent
            if hit is not None and t_split >= hit:
                reason = "too close to the obstacle to replan"
                say(reason)
                break
            t0 = time.monotonic()
            outcome = await plan_at(base, t_split)
            took = time.monotonic() - t0
            if not outcome.ok or outcome.route is None:
                return Swapped(outcome, t_split, outcome.message)
            if self.fleet_on() and self.control.active is base:
                why = await self.fleet.commit(splice(base, outcome.route.trajectory), what)
                if why is not None and self.fleet.clock_off is not None:
                    reason = why  # planning again would not help
                    say(why)
                    break
                if why is not None:
                    lost += 1
                    reason = why
                    say(why + ("; planning again against it" if lost < FLEET_TRIES else ""))
                    if lost >= FLEET_TRIES:
                        break
                    self.report.event("fleet", f"deconfliction: {why}; planning again against it", what=what)
                    continue
            if self.control.active is not base or self.control.route is not route:
                if self.fleet_on():
                    self.fleet.cancel()
                changed += 1
                reason = "the flown plan changed while planning (a stop or another change came first)"
                say(reason + "; planning again")
                continue
            if self.control.swap(splice(base, outcome.route.trajectory), t_split, arrived, what, outcome.route):
                return Swapped(outcome, t_split)
            if self.fleet_on():
                self.fleet.cancel()  # the candidate that won is not flown: its number is not published
            if self.control.refusal != SWAP_LATE:
                reason = self.control.refusal  # an internal check: planning again would not help
                say(reason)
                break
            late += 1
            reason = (f"planning took {took:.2f} s, more than the {ahead:.2f} s to its split time"
                      + (" twice: the computer is too busy to plan this in flight now" if late == 2 else ""))
            if late < 2:
                say(reason + "; planned again once, further ahead")
                ahead = min(max(2.0 * ahead, RETRY_MARGIN * took + 0.1), MAX_AHEAD)
            else:
                say(reason)
        return Swapped(None, reason=reason or "too close")

    def ahead_within(self, bounds: Bounds, ahead: float) -> float:
        """`ahead`, or further, to where the flown plan is back within `bounds` (plan_budget.ahead_within)."""
        active = self.control.active
        return ahead if active is None else ahead_within(active, self.control.committed(), bounds, ahead)

    # -- missions ---------------------------------------------------------------------------------

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
            outcome = self.logged(await self.runtime.plan(check_mission, replace(spec, raw={}), rest_jet(pos), 0.0,
                                                          self.known(), self.cfg))
            plan_ms = round((time.perf_counter() - t0) * 1000, 2)
            if not outcome.ok:
                self._reject_outcome(spec, outcome)
                return
        self.control.load(spec)
        where = "on the ground" if not self.flight.airborne else f"in {self.flight.state.value}"
        self.report.event("accepted", f"mission {spec.id} loaded ({len(spec.waypoints)} waypoints, vehicle {where}); "
                          "send 'start' to fly it", key="mission", mission=spec.id, plan_ms=plan_ms, pending=True)

    def _reject_outcome(self, spec: MissionSpec, outcome: Outcome) -> None:
        field = "" if outcome.blocked_waypoint is None else f"waypoints[{outcome.blocked_waypoint - spec.first_index}]"
        field = outcome.field or field
        why = outcome.message
        if outcome.status is OutcomeStatus.INFEASIBLE:  # not a mismatch, which no bound would fix
            why += self._clipped_note(spec)
        self.report.reject("mission", field, f"mission {spec.id}: {why}", mission=spec.id)

    @staticmethod
    def logged(outcome: Outcome) -> Outcome:
        """An outcome, its planner bug (an exception turned into a refusal: companion.mission.answered)
        logged with its traceback: never swallowed silently."""
        bug = outcome.stats.get("internal_error")
        if bug:
            log.error("planner failed (answered as a refusal): %s\n%s", outcome.message, bug)
        return outcome

    async def fly(self, spec: MissionSpec, arrived: float | None) -> bool:
        """Plan `spec` from the flown state a little ahead of now and fly it."""
        given = spec
        spec, _ = self.within_limits(spec, tell=False)  # limits read since it was loaded
        async with self.lock:
            n = len(spec.waypoints)

            # the anytime start: the default allocation at once, the search's plan later (improve)
            quick = [self.cfg.planner.anytime and spec.durations is None and self.cfg.planner.timing == "fastest"
                     and not self.fleet_on()]

            async def plan_at(base: Trajectory, t_split: float) -> Outcome:
                jet = self.control.jet(t_split)
                t0 = time.perf_counter()
                # the search is cut to what fits before the split (planner_core.fastest_durations:
                # a count, so a recording replays the same plan)
                # the swap takes a plan ready before t_split - lead: the time after what is committed
                left = t_split - self.control.committed() - (self.fleet.wait if self.fleet_on() else 0.0)
                cap = self.budget.candidates_within(n, left)
                # without a fleet the call is start_mission's own (what a recording names and replays)
                fn: Any = (partial(start_separated, neighbours=self.neighbours(spec.bounds), candidates=cap)
                           if self.fleet_on() else partial(start_mission, quick=True) if quick[0]
                           else partial(start_mission, candidates=cap) if cap else start_mission)
                out: Outcome = self.logged(await self.runtime.plan(fn, replace(spec, raw={}), jet, t_split,
                                                                   self.known(), self.cfg))
                self.plan_latency = time.perf_counter() - t0
                self.budget.measured(self.plan_latency, n, int(out.stats.get("candidates", 1)))
                quick[0] = quick[0] and out.ok  # the default allocation failed: the search, as without anytime
                return out

            ahead = self.budget.split_ahead_for(n) if quick[0] else self.budget.mission_ahead(n)
            done = await self._swap_at_split(f"mission {spec.id}", arrived, plan_at,
                                             ahead=self.ahead_within(spec.bounds, ahead))
            if not done.ok:
                if done.outcome is not None:
                    why = done.outcome.message
                    if self.fleet_on():
                        why = self.fleet.named(why) + self.fleet_note()
                    self._reject_outcome(spec, replace(done.outcome, message=why))
                else:
                    self.report.reject("mission", "", f"mission {spec.id}: {done.reason}", mission=spec.id)
                return False
            assert done.outcome is not None and done.outcome.route is not None
            self.user_timed = False
            self.control.unload(given)
            self.flight.handle(MissionStarted(spec.id))
            lat = self.plan_latency or 0.0
            delay = done.outcome.stats.get("fleet_delay")
            waits = f"; starts {delay:g} s later to keep the separation from the other vehicles" if delay else ""
            if done.outcome.stats.get("capped"):
                waits += (f"; the search for the fastest durations stopped after {done.outcome.stats['candidates']} "
                          f"candidate plans, what fits in [planner] search_time {self.cfg.planner.search_time:g} s "
                          "at the planning speed measured here (it may fly a little slower than a full search)")
            if quick[0]:
                waits += "; flying the default durations while the fastest are searched for (event `improved`)"
            self.report.event("accepted", f"mission {spec.id}: planned and verified in {lat * 1000:.1f} ms "
                              f"({len(spec.waypoints)} waypoints, {done.outcome.route.t_end - done.t_split:.2f} s)"
                              + waits, key="mission", mission=spec.id, plan_ms=round(lat * 1000, 2),
                              compute_ms=num(float(done.outcome.stats.get("plan_seconds", math.nan)) * 1000, 2),
                              **({"fleet_delay": delay} if delay else {}))
            if quick[0]:
                self._improving = asyncio.get_running_loop().create_task(self.improve(done.outcome.route))
            return True

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

        async def plan_at(base: Trajectory, t_split: float) -> Outcome:
            if superseded():
                return Outcome(False, message="the flown plan changed first")
            t0 = time.perf_counter()
            fn: Any = (partial(replan_remainder, allocate=True, candidates=cap) if cap < FULL_SEARCH
                       else partial(replan_remainder, allocate=True))
            out: Outcome = self.logged(await self.runtime.plan(fn, quick, base, t_split, self.known(), self.cfg))
            self.budget.measured(time.perf_counter() - t0, n, int(out.stats.get("candidates", 1)))
            if superseded():
                return Outcome(False, message="the flown plan changed first")
            if out.ok and out.route is not None and out.route.t_end > quick.t_end - IMPROVE_MIN:
                return Outcome(False, message=f"the search's plan lands no earlier ({out.route.t_end - t_split:.2f} s "
                               f"against {quick.t_end - t_split:.2f} s from the split)")
            return out

        t0 = time.perf_counter()
        done = await self._swap_at_split(f"{what} (fastest durations)", None, plan_at,
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

    # -- changes ------------------------------------------------------------------------------------

    async def on_change(self, change: Change, arrived: float) -> None:
        if self.route is None or not self.flight.flying_ours or not self.control.flying:
            why = ("the mission was interrupted by a stop: send 'resume' first" if self.interrupted is not None
                   else f"no mission in flight ({self.flight.state.value})")
            self.report.reject("change", "", why)
            return
        async with self.lock:
            refused: list[Refused] = []
            description: list[str] = []
            timed: list[bool] = [False]

            async def plan_at(base: Trajectory, t_split: float) -> Outcome:
                assert self.route is not None
                r = trim(self.route, self.control.now())
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
        durations were the planner's)."""
        messages = notes if notes is not None else []
        if local is not None:
            out: Outcome = self.logged(await self.runtime.run(self.runtime.replan_pool, local_replan, r, t_split,
                                                              local, self.known(), self.cfg,
                                                              self.neighbours(r.mission.bounds)))
            if out.ok:
                out.stats.setdefault("method", "local")
                return out
            messages.append(f"local replan: {out.message}")
        if on_fallback is not None:
            on_fallback()
        extra = () if remainder is None else remainder
        if allocate is None:
            allocate = self.allocates(r)
        # The fastest-allocation search is cut to what fits before the split, as a mission's is
        # (fly): the swap refuses a plan ready after t_split - lead, and a whole search (~30
        # candidate plans, each detour tried) took 0.45-0.5 s on the loaded 2-core machine for a
        # wall across a leg: past the 0.15 s to the split, and again past the braking deadline.
        n = len(r.waypoints) + 2  # a detour's two points
        cap = self.budget.candidates_within(n, t_split - self.control.committed()) if allocate else None
        kw: dict[str, Any] = {"candidates": cap} if cap else {}
        out = self.logged(await self.runtime.plan(partial(replan_remainder, allocate=allocate,
                                                          neighbours=self.neighbours(r.mission.bounds), **kw),
                                                  r, base, t_split, self.known(), self.cfg, *extra, urgent=True))
        if self.cfg.planner.fallback_delay > 0:
            await asyncio.sleep(self.cfg.planner.fallback_delay)
        out.stats["method"] = "detour" if out.stats.get("detour") else "remainder"
        if not out.ok:
            messages.append(f"full replan: {out.message}")
        return out

    def allocates(self, r: Route) -> bool:
        """Durations the mission did not give are the planner's to choose again from the split."""
        return r.mission.durations is None and self.cfg.planner.timing == "fastest" and not self.user_timed

    async def _replan_swapped(self, what: str, arrived: float, plan_at: Callable[[Trajectory, float], Awaitable[Outcome]],
                              hit: float | None = None, notes: list[str] | None = None) -> Swapped:
        """`_swap_at_split` for a replan: time it, say what was swapped in."""
        t0 = time.perf_counter()
        waited = time.monotonic() - arrived
        done = await self._swap_at_split(what, arrived, plan_at, hit=hit, notes=notes)
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
        names = str(ids)
        race = self.brakes.race_guard
        if race is not None and self.control.active is race.base and self.route is not None and self.control.flying:
            # A replan for an earlier pop-up holds the lock until it is swapped in or its
            # braking deadline: this obstacle may need the stop sooner.
            now = self.control.now()
            hit = first_hit(race.base, now, new, self.route.mission.radius)
            if hit is not None:
                race.bring_forward(brake_deadline(race.base, now, hit, self.route.mission.bounds), hit,
                             f"deadline brought forward by obstacles {names} (hit at t={hit:.2f} s)")
        async with self.lock:
            if self.flight.state is not S.STREAMING or self.route is None or not self.control.flying:
                announce()
                return
            active = self.control.active
            assert active is not None
            now = self.control.now()
            radius, split_ahead = self.route.mission.radius, self.cfg.planner.split_ahead
            hit = first_hit(active, now, new, radius)
            if hit is None:
                announce()
                self.report.event("obstacles_clear", f"obstacles {names}: the current trajectory stays clear; no replan",
                                  obstacles=ids)
                return
            if hit < self.control.committed() + split_ahead:  # setpoints up to now + lead are sent
                announce()
                await self.brakes.brake(f"obstacle {names} is {hit - now:.2f} s ahead: too close to replan", arrived)
                return
            await self._avoid_race(new, names, arrived, hit, announce)

    async def _avoid_race(self, new: list[Polytope], names: str, arrived: float, hit: float,
                          announce: Callable[[], None]) -> None:
        """Race the replan against the braking deadline: the latest start of a stop that ends
        before the flown plan would enter the obstacle. A verified stop is prepared in parallel
        (at once if the deadline is near, else when the local replan fails or runs late) and
        swapped in at its start unless a verified replan was swapped in first."""
        assert self.route is not None and self.control.active is not None
        base, bounds, now = self.control.active, self.route.mission.bounds, self.control.now()
        guard = StopGuard(base, hit)
        notes: list[str] = []
        edit = LocalEdit((AddObstacles(tuple(new)),), f"avoid obstacles {names}")
        what = f"obstacles {names}"

        async def plan_at(base_now: Trajectory, t_split: float) -> Outcome:
            assert self.route is not None
            r = trim(self.route, self.control.now())
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
        if self.flight.state is not S.STREAMING or self.route is None or not self.control.flying:
            self.report.event("fleet", f"deconfliction: {reason}; not flying a mission: nothing to replan")
            return
        asyncio.get_running_loop().create_task(self._fleet_replan(reason))

    def fleet_stop(self, reason: str) -> None:
        """Our clock is off the fleet's (companion.clocks): the mission flying, planned against the
        others' times, is stopped (a verified stop; a hold does not depend on the clock)."""
        if self.flight.state is S.STREAMING and self.control.flying:
            asyncio.get_running_loop().create_task(self.hold(f"fleet: {reason}", time.monotonic()))

    async def _fleet_replan(self, reason: str) -> None:
        arrived = time.monotonic()
        async with self.lock:
            if self.flight.state is not S.STREAMING or self.route is None or not self.control.flying:
                return

            async def plan_at(base: Trajectory, t_split: float) -> Outcome:
                assert self.route is not None
                r = trim(self.route, self.control.now())
                return await self._replan_outcome(r, base, t_split, None, None)

            done = await self._replan_swapped(f"fleet ({reason})", arrived, plan_at)
            if not done.ok:
                await self.brakes.brake(f"deconfliction: {reason}; no separated replan ({done.reason})", arrived)
