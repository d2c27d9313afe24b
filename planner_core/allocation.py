"""Minimum-time allocation under hard bounds (issue 12, item 2); a time weight; the takeoff climb.

`fastest_durations(problem)` chooses durations that make the plan as short as the
bounds and corridors allow for the planner, every candidate planned and verified:

0. knots: segment j of length L is split into K_j equal straight pieces,
   K_j = clip(ceil(knot_density sqrt(L a / v^2)), 1, max_pieces) where
   L a / v^2 >= KNOT_MIN_RATIO (0.18 for a single rest-to-rest leg) and both ends are slow (rest, or a turn capping the speed
   at SLOW_END v), else 1 (measured on 15 cluttered missions: knots elsewhere never
   shortened a plan and tripled the search time), with v, a the bounds
   along it (`timing.directional_bounds`). The knots lie on the straight segment, which
   the segment's corridor contains, so every piece keeps the parent's corridor; the
   trajectory still passes every given waypoint (`waypoint_index` says where). One
   degree-9 segment certified on its hodographs' pieces (constraints.HULL_PIECES) needs
   2.64 L / v for a rest-to-rest leg (7% over its true peak speed, 3.7x on one plain
   hull), and snap is certified 1.6x conservatively; knots still shorten long legs
   (measured in benchmarks/speed.py: 5-50 m along x and the diagonals within 1.11-1.22x ruckig
   on the binding axis, with step 1's profile-shaped start).
1. start from `timing.durations_from_lengths` with safety 1 on the knotted waypoints
   (the default allocation is that times 1.4); and, searched apart, from the same durations
   with each knotted segment's pieces in the proportions of the time-optimal stop-to-stop
   profile along it (`timing.stop_to_stop_crossings`: the times it passes the knots), for a
   single leg (on missions it never won: see `fastest_durations`). Equal
   pieces of a short leg need their end pieces much slower than the middle ones, which the
   safety-1 durations do not give and the refinement (shrink only) cannot find: a 5 m
   diagonal leg (v 3, a 3, j 10, s 50) flew 1.33x ruckig's time, 1.21-1.22x with both starts;
   the plain start stays better on some long legs (20 m diagonal 1.11x against 1.16x);
2. a uniform scale search on those durations: the smallest scale (to a relative
   `tol`) whose plan holds, bracketed by shrinking or doubling;
3. per-segment refinement: each segment in turn (longest first) tries its duration
   times `shrink` with the others kept, and keeps it when the plan holds; `rounds`
   passes, stopping at `max_plans` candidate plans in all.
4. the local pass: one plan at the safety-1 durations of step 1 with the planner's own local
   recovery on, in small steps (stretch factor LOCAL_STRETCH): only the windows that fail are
   stretched, each at O(window) cost, so a long mission pays about one plan where a uniform
   scale would be held back by its single tightest turn.

Steps 2-3 run only up to SEARCH_MAX_WAYPOINTS waypoints (after the knots): each of their ~20
candidates is a whole plan, and above that the local pass alone was as fast to fly for a
fraction of the cost (measured on benchmarks/scale.py's scenes without durations: at 100
waypoints the search took 12-16 plans' time for 172 s of flight, the local pass 3 plans' time
for 167 s; at 1000 waypoints 46 plans' time for 1986 s against 1.6 for 1804 s). Which one ran
is `strategy` ("search" or "local"), also in the stats. A second local pass (`local_passes=2`,
from the first one's durations times LOCAL_SHRINK) flies another 5-8% faster on those scenes
for 3-4x the first pass's cost (1000 waypoints: 1811 -> 1669 s, 94 -> 386 ms), so one is the
default.

Never slower than the default allocation: the default allocation of the problem as
given is planned first, and it is the answer unless a verified plan is shorter. The
answer carries the verified plan (`result`) and how it was found (`plans`, `time`).

`weighted_durations(problem, rho)` minimises J + rho T from the fastest allocation
(its docstring); `takeoff_duration(h, bounds)` is the certified minimum of a vertical
rest-to-rest climb, for the companion's takeoff (pure: no plan is run).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planner_core.problem import Bounds, FloatArray, Polytope, Problem
from planner_core.result import PlanResult, PlanStatus
from planner_core.timing import (
    DEFAULT_SAFETY,
    directional_bounds,
    durations_from_lengths,
    junction_speeds,
    stop_to_stop_crossings,
)

IntArray = NDArray[np.int64]
KNOT_DENSITY = 3.0  # measured (benchmarks/speed.py): 5-50 m legs within 1.11-1.22x ruckig (x and diagonals)
KNOT_MIN_RATIO = 1.0  # no knots on a segment shorter than v^2 / a (measured: shorter ones never paid in missions)
KNOT_MIN_RATIO_REST = 0.18  # ... or 0.18 v^2 / a when it starts and ends at rest (1 m legs in any direction at v 3, a 3: 1.27-1.33x ruckig, 1.44-1.5x unknotted)
MAX_PIECES = 12
MAX_PLANS = 16  # refinement stops at this many candidate plans in all (per search)
SEARCH_MAX_WAYPOINTS = 32  # measured (benchmarks/speed.py --scale): the search pays below, not above
LOCAL_STRETCH = 1.1  # the local pass: stretch factor of the planner's own local recovery ...
LOCAL_MAX_STRETCHES = 12  # ... and how often at one site (1.1^12 ~ 3.1)
LOCAL_SHRINK = 0.9  # a further local pass starts from the last one's durations times this
SLOW_END = 0.25  # an end this slow (fraction of v) counts as a stop for the knot rule

__all__ = ["FastestAllocation", "fastest_durations", "takeoff_duration", "weighted_durations"]


@dataclass(frozen=True)
class FastestAllocation:
    problem: Problem  # the input with the durations found
    result: PlanResult  # the verified plan at them (or the failure when nothing planned)
    durations: FloatArray
    scale: float  # uniform scale on the safety-1 durations after step 2 (0: the default won)
    plans: int  # candidate plans (each verified)
    time: float  # seconds
    waypoint_index: IntArray  # per given waypoint, its index in `problem` (knots between)
    strategy: str = "search"  # "search": steps 2-4; "local": step 4 alone (more than SEARCH_MAX_WAYPOINTS)

    @property
    def ok(self) -> bool:
        return self.result.ok


_NOT_PLANNED = PlanResult(PlanStatus.INFEASIBLE, None, "not planned: the candidate cap was reached")


def _with_durations(problem: Problem, d: FloatArray) -> Problem:
    return replace(problem, times=problem.times[0] + np.concatenate([[0.0], np.cumsum(d)]))


def knot_pieces(problem: Problem, density: float = KNOT_DENSITY, max_pieces: int = MAX_PIECES) -> IntArray:
    """(m-1,) pieces per segment (module docstring, step 0): knots only on a segment at least
    KNOT_MIN_RATIO v^2 / a long (KNOT_MIN_RATIO_REST for a single rest-to-rest leg) whose both
    ends are slow (the start or goal at rest, or a turn that caps the speed through it at
    SLOW_END v or less)."""
    d = np.diff(problem.waypoints, axis=0)
    lengths = np.linalg.norm(d, axis=1)
    units = np.where(lengths[:, None] > 1e-12, d / np.maximum(lengths, 1e-12)[:, None], 0.0)
    lim = np.minimum(directional_bounds(problem.bounds, units), 1e12)
    ramp = lim[:, 0] ** 2 / lim[:, 1]  # distance scale of a speed change
    x = lengths / np.maximum(ramp, 1e-12)
    caps = junction_speeds(units, lim[:, 0], float(np.linalg.norm(problem.initial[1])))
    caps[-1] = float(np.linalg.norm(problem.final[1]))
    slow_start = caps[:-1] <= SLOW_END * lim[:, 0]
    slow_end = caps[1:] <= SLOW_END * lim[:, 0]
    rest = np.zeros(lengths.size, dtype=bool)
    rest[0] = not np.any(problem.initial[1:])
    rest &= (lengths.size == 1) & (not np.any(problem.final[1:]))
    min_ratio = np.where(rest, KNOT_MIN_RATIO_REST, KNOT_MIN_RATIO)
    k = np.where((x >= min_ratio) & slow_start & slow_end, np.ceil(density * np.sqrt(x)), 1.0)
    return np.asarray(np.clip(np.nan_to_num(k, nan=1.0), 1, max_pieces), dtype=np.int64)


def _leg_pieces(problem: Problem, density: float = KNOT_DENSITY, max_pieces: int = MAX_PIECES) -> int:
    """The pieces of the first leg by the knot rule's length alone (its ends' speeds ignored)."""
    d = problem.waypoints[1] - problem.waypoints[0]
    length = float(np.linalg.norm(d))
    if length <= 1e-12:
        return 1
    lim = np.minimum(directional_bounds(problem.bounds, (d / length)[None, :]), 1e12)[0]
    x = length / max(float(lim[0] ** 2 / lim[1]), 1e-12)
    if not np.isfinite(x) or x < KNOT_MIN_RATIO_REST:
        return 1
    return int(np.clip(np.ceil(density * np.sqrt(x)), 1, max_pieces))


def insert_knots(problem: Problem, pieces: IntArray) -> tuple[Problem, IntArray]:
    """Split segment j into pieces[j] equal straight pieces, each with segment j's corridor and
    its duration split evenly; returns the problem and the new index of every given waypoint."""
    wps: list[FloatArray] = []
    dur: list[float] = []
    corr: list[Polytope | None] = []
    index: list[int] = []
    old = problem.durations
    for j in range(problem.m - 1):
        index.append(len(wps))
        k = int(pieces[j])
        for i in range(k):
            wps.append(problem.waypoints[j] + (problem.waypoints[j + 1] - problem.waypoints[j]) * (i / k))
            dur.append(old[j] / k)
            corr.append(problem.corridor(j))
    index.append(len(wps))
    wps.append(problem.waypoints[-1])
    corridors: tuple[Polytope | None, ...] | None = None if problem.corridors is None else tuple(corr)
    out = Problem(np.asarray(wps), problem.times[0] + np.concatenate([[0.0], np.cumsum(dur)]), problem.bounds,
                  problem.initial, problem.final, corridors)
    return out, np.asarray(index, dtype=np.int64)


def _profile_shaped(given: Problem, pieces: IntArray, index: IntArray, kbase: FloatArray) -> FloatArray:
    """The knotted segments' piece durations in the proportions of the time-optimal stop-to-stop
    profile along the segment (`timing.stop_to_stop_crossings`), each segment's total kept.

    The safety-1 durations of equal-length pieces give the end pieces too little of the time
    (their certificate minimum is for a whole rest-to-rest segment, the middle ones run at full
    speed): on a 5 m diagonal leg (v 3, a 3, j 10, s 50) the search then found 1.33x ruckig's
    time, 1.2x in these proportions (benchmarks/speed.py)."""
    split = np.flatnonzero(pieces > 1)
    if split.size == 0:
        return kbase
    d = np.diff(given.waypoints, axis=0)[split]
    lengths = np.linalg.norm(d, axis=1)
    lim = directional_bounds(given.bounds, d / np.maximum(lengths, 1e-12)[:, None])
    out = kbase.copy()
    for row, j in enumerate(split.tolist()):
        k = int(pieces[j])
        t = stop_to_stop_crossings(lengths[row : row + 1], lim[row : row + 1], np.linspace(0.0, 1.0, k + 1))[0]
        shape = np.diff(t)
        part = slice(int(index[j]), int(index[j]) + k)
        if np.all(shape > 0.0) and np.all(np.isfinite(shape)):
            out[part] = shape * (float(np.sum(kbase[part])) / float(np.sum(shape)))
    return out


def fastest_durations(
    problem: Problem,
    method: str = "iterative",
    *,
    tol: float = 0.01,
    refine: bool = True,
    shrink: float = 0.85,
    rounds: int = 1,
    knots: bool = True,
    knot_density: float = KNOT_DENSITY,
    max_plans: int = MAX_PLANS,
    search: bool | None = None,
    local_passes: int = 1,
    max_candidates: int | None = None,
    first_leg_knots: bool = False,
    **opts: Any,
) -> FastestAllocation:
    """Durations as short as the planner can fly them (module docstring). `problem.times`
    only supplies the start time; `opts` go to `plan` (recovery and diagnosis are off for
    the candidates). knots=False keeps the given waypoints only. `search`: run steps 2-3
    (None: only up to SEARCH_MAX_WAYPOINTS waypoints, or with the global method); the local
    pass (step 4) runs whenever the method is iterative, `local_passes` times (each further
    pass starts from the last one's durations times LOCAL_SHRINK).

    `max_candidates`: an anytime cap (the companion's, in flight: it sizes it from the time left
    to its split). Once this many candidates were planned and one of them holds, no further
    candidate is planned and the best verified one is the answer (stats: `capped`). The steps
    run in the order of what they gain most: the default allocation first, then the uniform
    scale, the refinement, the knots, the local pass. A count, not a clock: the same cap gives
    the same plan (a recording replays bit for bit).

    When nothing plans and the start is moving, the first leg is knotted whatever its ends
    (`first_leg_knots`) and everything is tried once more: one degree-9 segment cannot certify a
    long leg that starts by accelerating away from its end (10 m from 1.2 m/s^2 the other way,
    v 2.4, a 2.4: no duration plans it; 2-4 pieces do), and the knot rule above keeps knots off
    legs with a fast end (they never shortened a plan). A mission sent in flight failed so."""
    from planner_core.planning import plan

    if max_candidates is not None and max_candidates < 1:
        raise ValueError(f"max_candidates: must be >= 1 or None, got {max_candidates}")

    t_start = time.perf_counter()
    full = {**opts, "recover": False, "diagnose": False} if method == "iterative" else {**opts, "diagnose": False}
    quick = {**full, "fallback": False} if method == "iterative" else full
    given = problem
    plan_count = [0]
    held = [False]  # a candidate held: from then on the cap may stop the search

    def spent() -> bool:
        return max_candidates is not None and held[0] and plan_count[0] >= max_candidates

    def planned(p: Problem, d: FloatArray, thorough: bool = False) -> PlanResult:
        """One verified candidate: the compiled pass alone (a quick yes/no), or with the general
        path behind it (`thorough`, for the first candidate: the default allocation). Past the
        cap, a refusal without planning (the search then winds down at no cost)."""
        if spent():
            return _NOT_PLANNED
        plan_count[0] += 1
        res = plan(_with_durations(p, d), method, **quick)
        if not res.ok and thorough and quick is not full:
            plan_count[0] += 1
            res = plan(_with_durations(p, d), method, **full)
        held[0] = held[0] or res.ok
        return res

    default = durations_from_lengths(given.waypoints, given.bounds, initial_jet=given.initial,
                                     corridors=given.corridors)
    same = np.arange(given.m, dtype=np.int64)
    base = durations_from_lengths(given.waypoints, given.bounds, safety=1.0, initial_jet=given.initial,
                                  corridors=given.corridors)
    pieces = knot_pieces(given, knot_density)
    if first_leg_knots and given.m >= 2:
        pieces[0] = max(int(pieces[0]), _leg_pieces(given, knot_density))
    knotted, index, kbase = given, same, base
    if knots and int(pieces.max()) > 1:
        knotted, index = insert_knots(given, pieces)
        kbase = durations_from_lengths(knotted.waypoints, knotted.bounds, safety=1.0, initial_jet=knotted.initial,
                                       corridors=knotted.corridors)
    searching = method != "iterative" or (knotted.m <= SEARCH_MAX_WAYPOINTS if search is None else search)
    first: PlanResult | None = None
    if searching and np.allclose(default, base * DEFAULT_SAFETY, rtol=1e-12, atol=0.0):
        default = base * DEFAULT_SAFETY  # the search's first candidate is the default allocation
    else:
        first = planned(given, default, True)
    options: list[tuple[float, Problem, PlanResult, FloatArray, float, IntArray]] = []
    if first is not None and first.ok:
        options.append((float(np.sum(default)), given, first, default, 0.0, same))
    if searching:
        found = [(_search(given, base, planned, tol, refine, shrink, rounds, max_plans, plan_count), given, same)]
        if knotted is not given:
            found.append((_search(knotted, kbase, planned, tol, refine, shrink, rounds, plan_count[0] + max_plans,
                                  plan_count), knotted, index))
        if knotted is not given and given.m == 2:
            # a single leg: the same knots with the pieces' durations in the stop-to-stop profile's
            # proportions, the better start on short legs (step 1; on the 15 missions of
            # benchmarks/speed.py it never won and cost 16 more plans on 7 of them)
            shaped = _profile_shaped(given, pieces, index, kbase)
            found.append((_search(knotted, shaped, planned, tol, refine, shrink, rounds, plan_count[0] + max_plans,
                                  plan_count), knotted, index))
        for f, p, idx in found:
            if f is not None:
                options.append((float(np.sum(f[0])), p, f[1], f[0], f[2], idx))
    if method == "iterative":
        start = kbase
        for n in range(max(local_passes, 0)):
            if spent() or (max_candidates is not None and options and plan_count[0] >= max_candidates):
                break
            plan_count[0] += 1
            local = plan(_with_durations(knotted, start * (1.0 if n == 0 else LOCAL_SHRINK)), method,
                         **{**opts, "recover": True, "diagnose": False, "stretch_factor": LOCAL_STRETCH,
                            "max_stretches": LOCAL_MAX_STRETCHES})
            if not local.ok or local.trajectory is None:
                break
            d_local = np.diff(local.trajectory.times)
            # its stretches are the search's steps from the safety-1 start, in the knotted problem's
            # indices: kept apart, so that nobody reads them as stretches of durations a user gave
            st = dict(local.stats)
            steps = {k: st.pop(k) for k in ("recoveries", "stretched_durations") if k in st}
            local = replace(local, stats={**st, "local_pass": {**steps, "pass": n + 1}})
            options.append((float(np.sum(d_local)), knotted, local, d_local, 1.0, index))
            if n and np.sum(d_local) >= np.sum(start):
                break
            start = d_local
    strategy = "search" if searching else "local"
    if not options and knots and not first_leg_knots and given.m >= 2 and np.any(given.initial[1:3] != 0.0) \
            and _leg_pieces(given, knot_density) > int(pieces[0]):
        again = fastest_durations(problem, method, tol=tol, refine=refine, shrink=shrink, rounds=rounds, knots=knots,
                                  knot_density=knot_density, max_plans=max_plans, search=search,
                                  local_passes=local_passes, max_candidates=max_candidates, first_leg_knots=True,
                                  **opts)
        plan_count[0] += again.plans
        if again.ok:
            return _done(again.problem, again.result, again.durations, again.scale, plan_count[0], t_start,
                         again.waypoint_index, again.strategy, max_candidates)
    if not options:
        # nothing planned: the default allocation once more with the caller's options (diagnosis and
        # recovery on unless turned off), so that the failure names the binding bound in the given indices
        plan_count[0] += 1
        fail = plan(_with_durations(given, default), method, **opts)
        if fail.ok:
            return _done(given, fail, np.diff(fail.trajectory.times) if fail.trajectory is not None else default,
                         0.0, plan_count[0], t_start, same, strategy)
        return FastestAllocation(given, fail, default, 0.0, plan_count[0], time.perf_counter() - t_start, same,
                                 strategy)
    _, p, res, d, scale, idx = min(options, key=lambda o: o[0])
    return _done(p, res, d, scale, plan_count[0], t_start, idx, strategy, max_candidates)


def _search(
    problem: Problem,
    base: FloatArray,
    planned: Callable[[Problem, FloatArray, bool], PlanResult],
    tol: float,
    refine: bool,
    shrink: float,
    rounds: int,
    max_plans: int,
    count: list[int],
) -> tuple[FloatArray, PlanResult, float] | None:
    """Steps 2-3 on one problem: (durations, verified plan, uniform scale) or None."""
    best: tuple[FloatArray, PlanResult] | None = None

    def attempt(d: FloatArray, thorough: bool = False) -> bool:
        nonlocal best
        res = planned(problem, d, thorough)
        if res.ok:
            best = (d, res)
            return True
        return False

    hi = DEFAULT_SAFETY
    if attempt(base * hi, True):
        lo = hi
        while lo > 0.5:
            lo *= 0.8
            if not attempt(base * lo):
                break
            hi = lo
        else:
            lo = 0.0
    else:
        lo = hi
        while hi < 64.0:
            hi *= 2.0
            if attempt(base * hi):
                break
            lo = hi
        else:
            return None
    while lo > 0.0 and hi / lo > 1.0 + tol:
        mid = float(np.sqrt(lo * hi))
        if attempt(base * mid):
            hi = mid
        else:
            lo = mid
    assert best is not None  # every success sets best, and the last one is at base * hi
    d_best, res_best = best
    if refine and d_best.size > 1:
        for _ in range(rounds):
            improved = False
            for s in np.argsort(-d_best):
                if count[0] >= max_plans:
                    break
                cand = d_best.copy()
                cand[s] *= shrink
                if attempt(cand):
                    d_best, res_best = best
                    improved = True
            if not improved:
                break
    return d_best, res_best, hi


def _done(problem: Problem, res: PlanResult, d: FloatArray, scale: float, n_plans: int, t_start: float,
          index: IntArray, strategy: str, cap: int | None = None) -> FastestAllocation:
    elapsed = time.perf_counter() - t_start
    info = {"method": "fastest", "strategy": strategy, "scale": scale, "plans": n_plans, "time": elapsed,
            "segments": int(d.size), "waypoint_index": index.tolist(),
            "max_candidates": cap, "capped": cap is not None and n_plans >= cap}
    traj = res.trajectory
    stats = {**res.stats, "allocation": info}
    result = replace(res, stats=stats, trajectory=None if traj is None else replace(traj, stats=stats))
    return FastestAllocation(_with_durations(problem, d), result, d, scale, n_plans, elapsed, index, strategy)


# --- a time weight: min J + rho T ----------------------------------------------------------------

_COST_ORDER = {"snap": 4, "jerk": 3}


def weighted_durations(
    problem: Problem,
    time_weight: float,
    method: str = "iterative",
    *,
    tol: float = 0.02,
    rounds: int = 2,
    step: float = 0.2,
    max_plans: int = 48,
    knots: bool = True,
    **opts: Any,
) -> FastestAllocation:
    """Durations minimising J + time_weight * T (J: the plan's integrated squared snap, or jerk
    with cost="jerk"; T: the flight time), every candidate planned and verified.

    1. The fastest allocation (`fastest_durations`): the shortest durations that plan, the
       lower end of the search (a larger weight only pushes towards it).
    2. A uniform scale s >= 1 on them: with rest ends J(s) = J(1) s^-(2k-1) once no bound is
       active (time scaling maps plans to plans), so s* = ((2k-1) J(1) / (rho T(1)))^(1/2k) is
       the first guess; a golden-section search on log s around it, to a relative `tol`.
    3. Per-segment refinement: each segment's duration times (1 +- step), kept when the
       objective falls, `rounds` passes with the step halved each time.
    Stops at `max_plans` candidates after step 1. `stats["allocation"]` says what it did."""
    if not (np.isfinite(time_weight) and time_weight > 0.0):
        raise ValueError(f"time_weight: must be finite and > 0, got {time_weight}")
    from planner_core.constraints import integrated_cost
    from planner_core.planning import plan

    t_start = time.perf_counter()
    cost = str(opts.get("cost") or "snap")
    if cost not in _COST_ORDER:
        raise ValueError(f"cost: the time weight needs an integrated cost (snap or jerk), got {cost!r}")
    k = _COST_ORDER[cost]
    fast = fastest_durations(problem, method, knots=knots, **opts)
    if not fast.ok or fast.result.trajectory is None:
        return fast
    quick = {**opts, "recover": False, "diagnose": False}
    if method == "iterative":
        quick["fallback"] = False
    base = fast.problem
    seen: dict[bytes, tuple[float, PlanResult | None]] = {}
    count = [0]

    def objective(d: FloatArray) -> float:
        key = np.asarray(d, dtype=float).tobytes()
        hit = seen.get(key)
        if hit is not None:
            return hit[0]
        if count[0] >= max_plans:
            return np.inf
        count[0] += 1
        res = plan(_with_durations(base, d), method, **quick)
        if not res.ok or res.trajectory is None:
            seen[key] = (np.inf, None)
            return np.inf
        val = integrated_cost(res.trajectory.control_points, d, k) + time_weight * float(np.sum(d))
        seen[key] = (val, res)
        return val

    d1 = fast.durations
    traj = fast.result.trajectory
    j1 = integrated_cost(traj.control_points, d1, k)
    seen[d1.tobytes()] = (j1 + time_weight * float(np.sum(d1)), fast.result)
    guess = max(1.0, ((2 * k - 1) * j1 / (time_weight * float(np.sum(d1)))) ** (1.0 / (2 * k)))
    s_best = _golden_log(lambda sc: objective(d1 * sc), max(1.0, guess / 1.5), guess * 1.5, tol,
                         objective(d1 * guess), guess)
    if objective(d1) <= objective(d1 * s_best):
        s_best = 1.0
    d_best = d1 * s_best
    f_best = objective(d_best)
    f_scale = f_best
    scale_plans = count[0]
    delta = step
    for _ in range(rounds):
        improved = False
        for seg in np.argsort(-d_best):
            for sign in (1.0, -1.0):
                cand = d_best.copy()
                cand[seg] *= 1.0 + sign * delta
                f = objective(cand)
                if f < f_best:
                    d_best, f_best, improved = cand, f, True
                    break
        delta *= 0.5
        if not improved and delta < tol:
            break
    res = seen[d_best.tobytes()][1]
    assert res is not None  # f_best is finite: its plan is stored
    elapsed = time.perf_counter() - t_start
    info = {"method": "time-weight", "time_weight": float(time_weight), "cost": cost,
            "objective": float(f_best), "objective_scale": float(f_scale), "integrated_cost": float(f_best - time_weight * float(np.sum(d_best))),
            "flight": float(np.sum(d_best)), "scale": float(s_best), "scale_plans": scale_plans,
            "plans": fast.plans + count[0], "fastest_plans": fast.plans, "fastest_flight": float(np.sum(d1)),
            "time": elapsed, "segments": int(d_best.size), "waypoint_index": fast.waypoint_index.tolist()}
    stats = {**res.stats, "allocation": info}
    tr = res.trajectory
    result = replace(res, stats=stats, trajectory=None if tr is None else replace(tr, stats=stats))
    return FastestAllocation(_with_durations(base, d_best), result, d_best, float(s_best), fast.plans + count[0],
                             elapsed, fast.waypoint_index, fast.strategy)


def _golden_log(f: Callable[[float], float], lo: float, hi: float, tol: float, f_mid: float,
                mid: float) -> float:
    """Minimiser of f on [lo, hi] by golden-section search in log scale; `mid` (with f(mid)
    known) is the starting point. Widens hi while the minimum sits at the upper end."""
    best, f_best = mid, f_mid
    while np.isfinite(f_best) and f(hi) < f_best and hi < 1e3:  # the minimum is further out
        best, f_best = hi, f(hi)
        lo, hi = best, best * 1.5
    a, b = np.log(lo), np.log(hi)
    g = (np.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(float(np.exp(c))), f(float(np.exp(d)))
    while b - a > np.log1p(tol):
        if fc <= fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = f(float(np.exp(c)))
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = f(float(np.exp(d)))
    for x, fx in ((float(np.exp(c)), fc), (float(np.exp(d)), fd)):
        if fx < f_best:
            best, f_best = x, fx
    return best


# --- takeoff ------------------------------------------------------------------------------------


def takeoff_duration(height: float, bounds: Bounds, *, up: tuple[float, float, float] = (0.0, 0.0, -1.0),
                     tol: float = 0.002) -> float:
    """Shortest duration of a rest-to-rest vertical climb of `height` metres that the planner
    certifies under `bounds` (one degree-9 segment, which is fixed by its rest ends; `up` is the
    climb direction in the caller's frame: NED's -z by default). Pure: no plan is run.

    The segment scales with the duration, so every order's certificate is a power law in it and
    the answer is `timing.durations_from_lengths` at safety 1 (the certificate's exact minimum at
    rest ends), checked here against the certificate itself; `tol` only guards rounding."""
    from planner_core.bezier import segment_from_jets
    from planner_core.constraints import certified_points, polygon_excess
    from planner_core.problem import rest_jet

    if not (np.isfinite(height) and height > 0.0):
        raise ValueError(f"height: must be finite and > 0, got {height}")
    u = np.asarray(up, dtype=float)
    if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) < 1e-12:
        raise ValueError(f"up: expected a nonzero 3-vector, got {list(up)}")
    u = u / np.linalg.norm(u)
    wps = np.stack([np.zeros(3), height * u])
    (t,) = durations_from_lengths(wps, bounds, safety=1.0, min_duration=1e-6)
    ctrl = segment_from_jets(rest_jet(wps[0]), rest_jet(wps[1]), float(t))[None]
    for _ in range(8):  # the table's last digits: stretch until the certificate holds outright
        if all(np.all(certified_points(ctrl, k, np.array([t])) <= bounds.hi[k - 1])
               and np.all(certified_points(ctrl, k, np.array([t])) >= bounds.lo[k - 1])
               and not np.any(polygon_excess(certified_points(ctrl, k, np.array([t])),
                                             bounds.horizontal[k - 1], bounds.sides) > 0.0)
               for k in range(1, 5)):
            return float(t)
        t *= 1.0 + tol
        ctrl = segment_from_jets(rest_jet(wps[0]), rest_jet(wps[1]), float(t))[None]
    raise AssertionError("takeoff_duration: the certificate table disagrees with the certificate")
