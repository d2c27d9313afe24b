"""Minimum-time allocation under hard bounds (issue 12, item 2), on today's certificate.

`fastest_durations(problem)` chooses durations that make the plan as short as the
bounds and corridors allow for the planner, every candidate planned and verified:

0. knots: segment j of length L is split into K_j equal straight pieces,
   K_j = clip(ceil(knot_density sqrt(L a / v^2)), 1, max_pieces) where
   L a / v^2 >= KNOT_MIN_RATIO (0.3 for a single rest-to-rest leg) and both ends are slow (rest, or a turn capping the speed
   at SLOW_END v), else 1 (measured on 15 cluttered missions: knots elsewhere never
   shortened a plan and tripled the search time), with v, a the bounds
   along it (`timing.directional_bounds`). The knots lie on the straight segment, which
   the segment's corridor contains, so every piece keeps the parent's corridor; the
   trajectory still passes every given waypoint (`waypoint_index` says where). One
   degree-9 piece certified by its hodograph hull needs 9 L / v for a rest-to-rest
   leg (3.7x its true peak speed); pieces at cruise are certified exactly, so knots
   close most of that gap (measured in benchmarks/speed.py).
1. start from `timing.durations_from_lengths` with safety 1 on the knotted waypoints
   (the default allocation is that times 1.4);
2. a uniform scale search on those durations: the smallest scale (to a relative
   `tol`) whose plan holds, bracketed by shrinking or doubling;
3. per-segment refinement: each segment in turn (longest first) tries its duration
   times `shrink` with the others kept, and keeps it when the plan holds; `rounds`
   passes, stopping at `max_plans` candidate plans in all.

Never slower than the default allocation: the default allocation of the problem as
given is planned first, and it is the answer unless a verified plan is shorter. The
answer carries the verified plan (`result`) and how it was found (`plans`, `time`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planner_core.problem import FloatArray, Polytope, Problem
from planner_core.result import PlanResult
from planner_core.timing import (
    DEFAULT_SAFETY,
    directional_bounds,
    durations_from_lengths,
    junction_speeds,
)

IntArray = NDArray[np.int64]
KNOT_DENSITY = 3.0  # measured (benchmarks/speed.py): 5-50 m legs within 1.2-1.35x ruckig
KNOT_MIN_RATIO = 1.0  # no knots on a segment shorter than v^2 / a (measured: shorter ones never paid in missions)
KNOT_MIN_RATIO_REST = 0.3  # ... or 0.3 v^2 / a when it starts and ends at rest (a 1 m leg at v 3, a 3: 2.2x faster)
MAX_PIECES = 12
MAX_PLANS = 16  # refinement stops at this many candidate plans in all (per search)
SLOW_END = 0.25  # an end this slow (fraction of v) counts as a stop for the knot rule

__all__ = ["FastestAllocation", "fastest_durations"]


@dataclass(frozen=True)
class FastestAllocation:
    problem: Problem  # the input with the durations found
    result: PlanResult  # the verified plan at them (or the failure when nothing planned)
    durations: FloatArray
    scale: float  # uniform scale on the safety-1 durations after step 2 (0: the default won)
    plans: int  # candidate plans (each verified)
    time: float  # seconds
    waypoint_index: IntArray  # per given waypoint, its index in `problem` (knots between)

    @property
    def ok(self) -> bool:
        return self.result.ok


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
    **opts: Any,
) -> FastestAllocation:
    """Durations as short as the planner can fly them (module docstring). `problem.times`
    only supplies the start time; `opts` go to `plan` (recovery and diagnosis are off for
    the candidates). knots=False keeps the given waypoints only."""
    from planner_core.planning import plan

    t_start = time.perf_counter()
    full = {**opts, "recover": False, "diagnose": False} if method == "iterative" else {**opts, "diagnose": False}
    quick = {**full, "fallback": False} if method == "iterative" else full
    given = problem
    plan_count = [0]

    def planned(p: Problem, d: FloatArray, thorough: bool = False) -> PlanResult:
        """One verified candidate: the compiled pass alone (a quick yes/no), or with the general
        path behind it (`thorough`, for the first candidate: the default allocation)."""
        plan_count[0] += 1
        res = plan(_with_durations(p, d), method, **quick)
        if not res.ok and thorough and quick is not full:
            plan_count[0] += 1
            res = plan(_with_durations(p, d), method, **full)
        return res

    default = durations_from_lengths(given.waypoints, given.bounds, initial_jet=given.initial,
                                     corridors=given.corridors)
    same = np.arange(given.m, dtype=np.int64)
    base = durations_from_lengths(given.waypoints, given.bounds, safety=1.0, initial_jet=given.initial,
                                  corridors=given.corridors)
    first: PlanResult | None = None
    if np.allclose(default, base * DEFAULT_SAFETY, rtol=1e-12, atol=0.0):
        default = base * DEFAULT_SAFETY  # the search's first candidate is the default allocation
    else:
        first = planned(given, default, True)
    found = [_search(given, base, planned, tol, refine, shrink, rounds, max_plans, plan_count)]
    pieces = knot_pieces(given, knot_density)
    index = same
    knotted = given
    if knots and int(pieces.max()) > 1:
        knotted, index = insert_knots(given, pieces)
        kbase = durations_from_lengths(knotted.waypoints, knotted.bounds, safety=1.0, initial_jet=knotted.initial,
                                       corridors=knotted.corridors)
        found.append(_search(knotted, kbase, planned, tol, refine, shrink, rounds,
                             plan_count[0] + max_plans, plan_count))
    options: list[tuple[float, Problem, PlanResult, FloatArray, float, IntArray]] = []
    if first is not None and first.ok:
        options.append((float(np.sum(default)), given, first, default, 0.0, same))
    for f, (p, idx) in zip(found, ((given, same), (knotted, index)), strict=False):
        if f is not None:
            options.append((float(np.sum(f[0])), p, f[1], f[0], f[2], idx))
    if not options:
        fail = first if first is not None else planned(given, default, True)
        return FastestAllocation(given, fail, default, 0.0, plan_count[0], time.perf_counter() - t_start, same)
    _, p, res, d, scale, idx = min(options, key=lambda o: o[0])
    return _done(p, res, d, scale, plan_count[0], t_start, idx)


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
          index: IntArray) -> FastestAllocation:
    elapsed = time.perf_counter() - t_start
    info = {"method": "fastest", "scale": scale, "plans": n_plans, "time": elapsed, "segments": int(d.size),
            "waypoint_index": index.tolist()}
    traj = res.trajectory
    stats = {**res.stats, "allocation": info}
    result = replace(res, stats=stats, trajectory=None if traj is None else replace(traj, stats=stats))
    return FastestAllocation(_with_durations(problem, d), result, d, scale, n_plans, elapsed, index)
