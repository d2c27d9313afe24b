"""Braking: verified stops, the braking deadline, and the race between a replan and a stop.

After a pop-up obstacle on the flown path, either a verified replan is swapped in or, by the
braking deadline (time to hit minus a stop and a margin), a verified stop planned in
parallel; a nearer pop-up meanwhile brings the deadline forward. The pure part (`plan_stop`,
`brake_deadline`) runs in worker threads; `Brakes` runs the race on the loop, its decisions (and
the deadline's) one pure function, companion.race_rules.race_step, each call recorded.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from companion import choice_rules as cr
from companion.config import Config
from companion.control import Control, jet_on
from companion.flight import HOLDING_CONTROL
from companion.race_rules import (
    DONE,
    NONE,
    PLANNING,
    Action,
    Brake,
    Braked,
    Deadline,
    Forward,
    Forwarded,
    GiveUp,
    Observation,
    Prepare,
    PreparedSwap,
    RaceRules,
    RaceState,
    ReplanCancelled,
    ReplanOver,
    SwapPrepared,
    Tick,
    Wait,
    Won,
    first_state,
    race_step,
    racing,
)
from companion.report import Reporter
from companion.route import build_corridors
from companion.rule_run import RuleRun, Runs
from companion.runtime import Runtime
from companion.supervisor import Braking, Supervisor
from companion.traffic import named_neighbours
from companion.wire.encode import vec
from companion.wire.messages import MissionSpec
from planner_core import (
    Bounds,
    CorridorError,
    FloatArray,
    Neighbours,
    Polytope,
    Trajectory,
    braking_trajectory,
    certify_all,
    segment_at,
    splice,
    stop_time_scale,
)

log = logging.getLogger("companion")

# the navigator's plan choices (companion.choice_rules): one numbering and observer for the
# starts, replans and stops of a run of the service
ChoiceRuns = Runs[cr.Rules, cr.ChoiceState, cr.Observation, cr.Action]


def choice_runs() -> ChoiceRuns:
    return Runs(cr.choice_step, "plan choice")


# A snap-limited stop takes about a second even from a slow speed (measured: the braking QP's
# durations grow 0.2 s * 1.5^k and slow stops land at k = 4), longer from speed.
MIN_STOP_SECONDS = 1.0
STOP_SAFETY_FACTOR = 1.5
BRAKE_MARGIN_SECONDS = 0.1
# A stop planned for "now" starts this far ahead at least (its QPs take 15-30 ms).
BRAKE_LEAD = 0.08


# -- pure: stops and deadlines --------------------------------------------------------------


def brake(jet: FloatArray, bounds: Bounds, corridor: Polytope | None, t0: float) -> tuple[Trajectory | None, str]:
    """A verified stop to rest from `jet` at t0 inside `corridor` (None and why, if none)."""
    result = braking_trajectory(jet, bounds, corridor, t0)
    if not result.ok or result.trajectory is None:
        return None, result.message
    # braking_trajectory certifies its result with verify() before returning it.
    return result.trajectory, result.message


def stop_time_estimate(velocity: FloatArray, acceleration: FloatArray, bounds: Bounds) -> float:
    """A generous estimate (s) of a verified stop from any of the states (n, 3): the braking
    planner's time scale (`stop_time_scale`), scaled, never below MIN_STOP_SECONDS."""
    return float(max(MIN_STOP_SECONDS, STOP_SAFETY_FACTOR * stop_time_scale(velocity, acceleration, bounds)))


def brake_deadline(traj: Trajectory, t_now: float, t_hit: float, bounds: Bounds) -> float:
    """Latest trajectory time at which to start braking, given that `traj` enters an obstacle at
    t_hit: the time to hit minus a stop (estimated from the states between now and the hit) and
    a margin. It may lie in the past: brake at once then."""
    ts = np.linspace(t_now, max(t_now, min(t_hit, traj.t_end)), 9)
    stop = stop_time_estimate(traj.evaluate(ts, 1), traj.evaluate(ts, 2), bounds)
    return t_hit - stop - BRAKE_MARGIN_SECONDS


@dataclass(frozen=True)
class StopPlan:
    trajectory: Trajectory | None  # verified stop to rest, starting at `start` (None: none found)
    start: float
    message: str
    in_free_space: bool  # False: only the dynamic bounds were respected (last resort)
    # in a fleet: certified separated from the other vehicles' live trajectories (None: no fleet,
    # or a last resort that was not checked; the trajectory's certificates are made when published)
    separated: bool | None = None


_jet_at = jet_on  # the one copy (companion.control): a flown plan's jet, at rest past its end


def corridor_at(traj: Trajectory, t: float) -> Polytope | None:
    if traj.corridors is None:
        return None
    return traj.corridors[segment_at(traj.times, t)]


def safe_corridor(position: FloatArray, velocity: FloatArray, obstacles: Sequence[Polytope],
                  mission: MissionSpec) -> Polytope | None:
    """A free polytope around `position` (for braking) that excludes every obstacle."""
    speed = float(np.linalg.norm(velocity))
    step = velocity / max(speed, 1e-9) * 1e-3 if speed > 1e-6 else np.array([1e-3, 0, 0])
    try:
        return build_corridors(np.vstack([position, position + step]), obstacles, mission)[0]
    except (CorridorError, ValueError):
        return None


# A stop that is not separated from another vehicle's live trajectory is tried stretched (longer
# stops from the same state rest elsewhere: the braking QP picks their end), then from earlier
# starts (it rests short of where the others pass); each is a verified stop like the first.
EARLIER_STARTS = (0.5, 0.0)  # fractions of the way from the earliest possible start to the asked one
STRETCHES = (1.5, 2.5)


def separation_failure(traj: Trajectory, neighbours: Neighbours | None, names: Sequence[str] = ()) -> str:
    """Why `traj` (and the hold at its end) is not separated from the other vehicles' live
    trajectories ("" when it is, or when there are none), the vehicle named."""
    if neighbours is None or not neighbours.trajectories:
        return ""
    _, failure, _ = certify_all(traj, neighbours)
    return "" if failure is None else named_neighbours(failure.message, names)


def _separated_stop(jet: FloatArray, bounds: Bounds, corridor: Polytope, t_b: float, first: Trajectory, said: str,
                    neighbours: Neighbours, names: Sequence[str]) -> tuple[Trajectory | None, str]:
    """The first of the stop from `jet` (`first`, its message `said`) and its stretched variants
    that is separated, with its message (None and why the first one is not, if none is)."""
    why = separation_failure(first, neighbours, names)
    if not why:
        return first, said
    durations = np.diff(first.times)
    for k in STRETCHES:
        result = braking_trajectory(jet, bounds, corridor, t_b, durations=(durations * k).tolist())
        if result.ok and result.trajectory is not None and not separation_failure(result.trajectory, neighbours, names):
            return result.trajectory, (f"{result.message} (its durations x{k:g}: the shortest stop from there was not "
                                       f"separated: {why})")
    return None, why


def plan_stop(base: Trajectory, starts: Sequence[float], clock: Callable[[], float], obstacles: Sequence[Polytope],
              mission: MissionSpec | None, bounds: Bounds, lead: float, neighbours: Neighbours | None = None,
              names: Sequence[str] = ()) -> StopPlan:
    """A verified stop branching off `base` at the latest of `starts` that works.

    `clock()` is the trajectory time now (this runs in a worker thread while `base` is being
    flown): a start is never earlier than clock() + lead, and a stop whose computation ran past
    its start (a busy computer) is planned again further ahead. Each start is tried inside a
    free corridor around the vehicle that excludes every obstacle (inflated by the vehicle
    radius), so the stop cannot enter one. If none works, the last resorts (`in_free_space`
    False, and the message says so) are a stop as soon as possible inside the corridor of the
    flown segment (planned before the newest obstacles), then within the dynamic bounds alone.

    In a fleet (`neighbours`: the other vehicles' live trajectories, local frame and flight
    time; `names` for messages) the stop and the hold at its end must also be certified
    separated from every one of them: a stop that is not is tried stretched, then from earlier
    starts (never earlier than clock() + lead: the flown plan up to there was certified with
    them); when none is, the first verified stop is flown and its message says from which
    vehicle it is not separated (`separated` False).
    """
    reasons: list[str] = []
    tried: set[float] = set()
    fallback: StopPlan | None = None
    wanted = sorted(starts, reverse=True)
    if neighbours is not None and neighbours.trajectories and wanted:
        soonest = clock() + lead
        wanted += [soonest + f * (wanted[-1] - soonest) for f in EARLIER_STARTS if wanted[-1] - soonest > 0.05]
    for want in wanted:
        for _ in range(3):
            began = clock()
            t_b = max(float(want), began + lead)
            if round(t_b, 4) in tried:
                break
            tried.add(round(t_b, 4))
            jet = _jet_at(base, t_b)
            corridor = safe_corridor(jet[0], jet[1], obstacles, mission) if mission is not None else None
            if corridor is None:
                reasons.append(f"start t={t_b:.3f} s: no free corridor around the vehicle")
                break
            traj, why = brake(jet, bounds, corridor, t_b)
            if traj is None:
                reasons.append(f"start t={t_b:.3f} s: {why}")
                break
            if neighbours is not None and neighbours.trajectories:
                found, note = _separated_stop(jet, bounds, corridor, t_b, traj, why, neighbours, names)
                if found is None:
                    if fallback is None:
                        fallback = StopPlan(traj, t_b, f"{why}; not separated from the other vehicles: {note}", True,
                                            separated=False)
                    reasons.append(f"start t={t_b:.3f} s: not separated: {note}")
                    break
                traj, why = found, note
            if clock() <= t_b - 0.5 * lead:
                return StopPlan(traj, t_b, why, True, separated=None if neighbours is None else True)
            # Planned too slowly to be swapped in before its start: plan further ahead.
            lead = max(lead, 2.0 * (clock() - began))
    if fallback is not None and fallback.trajectory is not None and clock() <= fallback.start - 0.5 * lead:
        return fallback
    detail = "; ".join(reasons) or "no start given"
    t_b = clock() + lead
    jet = _jet_at(base, t_b)
    flown = corridor_at(base, t_b)
    if flown is not None:
        traj, why = brake(jet, bounds, flown, t_b)
        if traj is not None:
            return StopPlan(traj, t_b, f"no stop fits a free corridor ({detail}); stopping inside the flown "
                            "segment's corridor", False)
    traj, why = brake(jet, bounds, None, t_b)
    if traj is None:
        return StopPlan(None, t_b, f"{detail}; without a corridor: {why}", False)
    return StopPlan(traj, t_b, f"no stop fits a free corridor ({detail}); shortest stop within the "
                    "dynamic bounds only", False)


def warm_up_brake(cfg: Config) -> bool:
    """A stop from speed next to an obstacle: first-call costs of the braking path paid early."""
    from companion.mission import start_mission
    from companion.obstacles import Known
    from companion.wire.messages import mission_from_message
    from planner_core import rest_jet

    spec = mission_from_message({"id": "warm-up", "waypoints": [[3.0, 0.0, -1.5]]}, cfg)
    outcome = start_mission(spec, rest_jet(np.array([0.0, 0.0, -1.5])), 0.0, Known(), cfg)
    if not outcome.ok or outcome.route is None:
        return False
    traj = outcome.route.trajectory
    eye = np.eye(3)
    box = Polytope(np.vstack([eye, -eye]), np.array([2.6, 0.5, -1.0, -2.4, 0.5, 2.0]))
    mid = 0.5 * (traj.t0 + traj.t_end)
    return plan_stop(traj, [mid], lambda: traj.t0, [box], spec, spec.bounds, 0.05).trajectory is not None


# -- on the loop: the race ------------------------------------------------------------------


@dataclass(frozen=True)
class StopContext:
    """What a stop is planned against: the flown mission (None: none), obstacles, bounds, and
    in a fleet the other vehicles' live trajectories (with their names, for messages)."""

    mission: MissionSpec | None
    obstacles: tuple[Polytope, ...]
    bounds: Bounds
    neighbours: Neighbours | None = None
    names: tuple[str, ...] = ()


@dataclass(frozen=True)
class Replanned:
    ok: bool
    reason: str = ""
    blocked: int | None = None  # mission index of a blocked waypoint
    blocked_message: str = ""


# each call of a pop-up's rules, shown to the flight recorder (companion.tap.Tap.race_step):
# (race, step, rules, state before, observation, state after, action)
RaceObserver = Callable[[int, int, RaceRules, RaceState, Observation, RaceState, Action], None]


RaceSteps = RuleRun[RaceRules, RaceState, Observation, Action]


def race_run(rules: RaceRules, number: int = 0, observe: RaceObserver | None = None,
             state: RaceState | None = None) -> RaceSteps:
    """One pop-up's decisions (companion.race_rules.race_step): the rules' state, stepped here
    only, each call shown to the flight recorder with the race's number (0: not recorded)."""
    return RuleRun(race_step, rules, first_state() if state is None else state, "race", number, observe)


class StopGuard:
    """What one race knows: the flown plan it guards, the race's decisions (`steps`: the braking
    deadline among them), and the verified stop for that deadline once `Brakes` plans it (in
    the brake thread).

    It knows nothing of who plans or flies the stop: `Brakes`, which runs the race, starts the
    planning (at the deadline less BRAKE_PREPARE, or at once when asked with `prepare`) and
    swaps the stop in; the guard never calls back into it. The deadline starts at the hit (no
    stop may start later) and is only brought forward, by `bring_forward`, its one writer, as
    the race's rules decide (companion.race_rules)."""

    def __init__(self, base: Trajectory, hit: float) -> None:
        self.base = base
        # unrecorded until the pop-up that races hands over its own (Replans.avoid)
        self.steps = race_run(RaceRules("", "", 0.0, 0.0), state=racing(hit))
        self.future: asyncio.Future[StopPlan] | None = None
        # set by `prepare`: the race wakes on it and starts the stop at once (created on the loop)
        self._asked: asyncio.Future[None] | None = None

    @property
    def deadline(self) -> float:
        """The latest trajectory time at which the stop may start."""
        deadline = self.steps.state.deadline
        assert deadline is not None
        return deadline

    @property
    def hit(self) -> float:
        hit = self.steps.state.hit
        assert hit is not None
        return hit

    @property
    def notes(self) -> tuple[str, ...]:
        """What brought the deadline forward."""
        return self.steps.state.notes

    def bring_forward(self, deadline: float, hit: float, names: str = "") -> None:
        """The braking deadline for an obstacle hit at `hit` (the first one's, or another,
        nearer obstacle's that arrived during the race, `names` its ids): brake for it in time."""
        stop, start = self.seen()
        forwarded = self.steps.step(Forward(deadline, hit, names, stop, start))
        if isinstance(forwarded, Forwarded) and forwarded.cancel and self.future is not None:
            self.future.cancel()  # planned for the later deadline (or still planning for it)
            self.future = None

    def seen(self) -> tuple[str, float | None]:
        """The stop for the deadline as the rules see it: none, planning or done, and its start
        when done with a trajectory."""
        plan = self.ready()
        stop = NONE if self.future is None else DONE if self.future.done() else PLANNING
        return stop, None if plan is None or plan.trajectory is None else plan.start

    def prepare(self) -> None:
        """Have the stop planned now rather than just before the deadline (the local replan
        failed or runs late): the race starts it on its next turn."""
        asked = self.asked()
        if not asked.done():
            asked.set_result(None)

    def asked(self) -> asyncio.Future[None]:
        """Done once `prepare` was called and the planning has not started since."""
        if self._asked is None:
            self._asked = asyncio.get_running_loop().create_future()
        return self._asked

    def planning(self, future: asyncio.Future[StopPlan]) -> None:
        """The stop for the deadline is being planned (by `Brakes`): a request is answered."""
        self.future = future
        self._asked = None

    def ready(self) -> StopPlan | None:
        f = self.future
        if f is None or not f.done() or f.cancelled() or f.exception() is not None:
            return None
        return f.result()

    def start_time(self) -> float:
        """When the stop starts: planned, or the deadline while it is not known yet."""
        plan = self.ready()
        return self.deadline if plan is None or plan.trajectory is None else plan.start

    def cancel(self) -> None:
        if self.future is not None:
            self.future.cancel()


class Brakes:
    """Stops on the loop: now (`brake`), or racing a replan against the braking deadline (`race`).

    `context()` says what a stop is planned against; `position()` is the measured position
    (for a hold when no stop can be planned). A stop swapped in (or a hold) interrupts the
    mission flown at its start: `Control` keeps what is left of it for `resume`."""

    def __init__(self, cfg: Config, flight: Supervisor, control: Control, runtime: Runtime, report: Reporter,
                 context: Callable[[], StopContext], position: Callable[[], FloatArray],
                 choices: ChoiceRuns | None = None) -> None:
        self.cfg = cfg
        self.flight = flight
        self.control = control
        self.runtime = runtime
        self.report = report
        self.context = context
        self.position = position
        self.race_guard: StopGuard | None = None  # the replan racing a braking deadline, if any
        self.races = itertools.count(1)  # each pop-up's number, for the records of its steps
        # each call of a pop-up's rules shown to the flight recorder; the service connects its tap
        self.observe: RaceObserver = lambda *_call: None
        self.choices = choices if choices is not None else choice_runs()  # stop, prepared or hold

    def race_steps(self, names: str) -> RaceSteps:
        """The decisions of a pop-up of obstacles `names` (and of the race that may follow), numbered."""
        rules = RaceRules(names, f"obstacles {names}", self.cfg.planner.split_ahead, self._spare())
        return race_run(rules, next(self.races), self.observe)

    def _spare(self) -> float:
        # Swap with a few periods to spare: the loop may be late, and swap() refuses a split
        # less than half a period ahead.
        return 2.0 / self.cfg.setpoints.rate_hz

    def _prepare(self, guard: StopGuard) -> None:
        """Plan the stop for the guard's deadline, unless it is planned (or planning) already."""
        if guard.future is None:
            guard.planning(self.stop_future(guard.base, [guard.deadline]))

    async def _prepared(self, guard: StopGuard) -> StopPlan | None:
        """The stop for the deadline (planned now if it was not), None if its planning failed."""
        self._prepare(guard)
        assert guard.future is not None
        try:
            return await guard.future
        except Exception as exc:  # a planner bug: the caller falls back to a fresh stop
            log.exception("stop planning failed: %r", exc)
            return None

    def stop_future(self, base: Trajectory, starts: list[float]) -> asyncio.Future[StopPlan]:
        """Plan a verified stop off `base` in the brake thread (see plan_stop)."""
        loop = self.runtime.loop
        assert loop is not None
        ctx = self.context()
        lead = max(BRAKE_LEAD, 3.0 / self.cfg.setpoints.rate_hz)
        return loop.run_in_executor(self.runtime.brake_pool, plan_stop, base, starts, self.control.clock(),
                                    list(ctx.obstacles), ctx.mission, ctx.bounds, lead, ctx.neighbours, ctx.names)

    def _commit(self, base: Trajectory, plan: StopPlan | None, arrived: float | None) -> bool:
        if plan is None or plan.trajectory is None or self.control.active is not base:
            return False
        return self.control.swap(splice(base, plan.trajectory), plan.start, arrived, "braking")

    async def brake(self, reason: str, arrived: float | None, blocked: int | None = None,
                    prepared: StopPlan | None = None) -> None:
        """Fly a verified stop inside a free corridor, starting as soon as one is planned; else
        the `prepared` one if it still starts ahead; else hold at the measured position. Say why.
        Which, is companion.choice_rules' (a stop's run); this observes and carries out."""
        run = self.choices.run(cr.StopRules(prepared is not None), cr.ChoiceState())
        action = run.step(cr.Ask(self.control.flying))
        if isinstance(action, cr.Nothing):
            return
        base = self.control.active
        assert base is not None
        try:
            plan = await self.stop_future(base, [self.control.now()])
        except Exception as exc:  # a planner bug must still end in a hold, not in flying on
            log.exception("stop planning failed")
            plan = StopPlan(None, self.control.now(), f"stop planning failed: {exc!r}", False)
        swapped = self._commit(base, plan, arrived)
        action = run.step(cr.Answer(swapped, "", plan.message, self.control.flying))
        if isinstance(action, cr.Plan):
            assert action.call == cr.PREPARED and prepared is not None
            swapped = self._commit(base, prepared, arrived)
            plan = prepared
            action = run.step(cr.Answer(swapped, "", prepared.message, self.control.flying))
        if isinstance(action, cr.Nothing):
            return
        if isinstance(action, cr.Hold):
            self.control.hold_here(self.position())
        assert isinstance(action, cr.Take | cr.Hold)
        self.flight.handle(Braking(reason))
        self.report.event("braking", f"{reason}; braking to a stop and holding", reason=reason,
                          blocked_waypoint=blocked, detail=action.detail,
                          **stop_fields(plan if isinstance(action, cr.Take) else None))

    async def race(self, guard: StopGuard, replan: asyncio.Task[Replanned], notes: list[str],
                   arrived: float, what: str) -> None:
        """Wait for the replan until the stop's start (a few periods to spare); brake if it is
        late or fails. The caller brought guard's deadline forward from the hit."""
        self.race_guard = guard
        try:
            await self._race(guard, replan, notes, arrived, what)
        finally:
            self.race_guard = None

    async def _race(self, guard: StopGuard, replan: asyncio.Task[Replanned], notes: list[str],
                    arrived: float, what: str) -> None:
        """Each turn observes, asks the race's rules (companion.race_rules) and carries out."""
        steps = guard.steps
        if steps.number == 0:  # a guard no pop-up handed its decisions to: this race's givens
            steps.rules = replace(steps.rules, what=what, spare=self._spare())
        flight = self.flight
        while True:
            if replan.done():
                failed = None if replan.cancelled() else replan.exception()
                if failed is not None:
                    log.error("replan failed: %r", failed)
                result = Replanned(False) if failed is not None else replan.result()
                action = steps.step(ReplanOver(result.ok, result.reason, result.blocked, result.blocked_message,
                                               "" if failed is None else repr(failed)))
                break
            held = flight.state in HOLDING_CONTROL
            stop, start = guard.seen()
            action = steps.step(Tick(held, flight.state.value, stop,
                                     held and guard.future is None and guard.asked().done(), start,
                                     self.control.committed() if held else None))
            if isinstance(action, GiveUp):  # e.g. a pilot took over meanwhile
                replan.cancel()
                guard.cancel()
                return
            if isinstance(action, Deadline | Wait) and action.prepare:  # asked for: planned at once
                self._prepare(guard)
            if isinstance(action, Prepare):
                self._prepare(guard)
                continue
            if isinstance(action, Deadline):
                break
            assert isinstance(action, Wait)
            waiting: set[asyncio.Future[Any]] = {replan}
            if action.asked:
                waiting.add(guard.asked())  # wake as soon as the stop is asked for
            if action.stop and guard.future is not None:
                waiting.add(guard.future)
            await asyncio.wait(waiting, timeout=action.timeout, return_when=asyncio.FIRST_COMPLETED)
        if isinstance(action, Won):
            guard.cancel()
            return
        if isinstance(action, Brake):
            await self.brake(action.reason, arrived, blocked=action.blocked,
                             prepared=guard.ready() if action.prepared else None)
            return
        replan.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await replan
        action = steps.step(ReplanCancelled(tuple(notes)))
        assert isinstance(action, SwapPrepared)
        await self._brake_at_deadline(guard, arrived)

    async def _brake_at_deadline(self, guard: StopGuard, arrived: float) -> None:
        """The replan is late: swap in the prepared stop (planned for the deadline)."""
        plan = await self._prepared(guard)
        swap_time = self.control.now()
        swapped = self._commit(guard.base, plan, arrived)
        action = guard.steps.step(PreparedSwap(swapped, None if plan is None else plan.message))
        if isinstance(action, Brake):
            await self.brake(action.reason, arrived)
            return
        assert isinstance(action, Braked) and plan is not None
        self.flight.handle(Braking(action.reason))
        self.report.event("braking", f"{action.reason}; braking to a stop and holding", reason=action.reason,
                          blocked_waypoint=None, detail=plan.message, deadline=round(action.deadline, 4),
                          hit_time=round(action.hit, 4), swap_time=round(swap_time, 4), **stop_fields(plan))


def stop_fields(plan: StopPlan | None) -> dict[str, Any]:
    if plan is None or plan.trajectory is None:
        return {}
    return {"brake_start": round(plan.start, 4), "stop_time": round(plan.trajectory.t_end, 4),
            "stop_position": vec(plan.trajectory.control_points[-1, -1]), "in_free_space": plan.in_free_space,
            **({} if plan.separated is None else {"separated": plan.separated})}
