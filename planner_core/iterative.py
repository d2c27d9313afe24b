"""The paper's iterative planner as a receding window of jet QPs (method.md, section 3).

At waypoint j the QP's unknowns are the jets of waypoints j .. j+H-1 (clipped
at m-2); it fully constrains every segment those jets determine, half
constrains the segment after the window and minimises integrated squared snap
over the fully determined segments. Only the jet at j is committed. H = 1 is
the paper's pass (one 12-unknown QP per waypoint).

Hot path: with the dense backend and an integrated cost, each window QP goes
through `window.WindowSolver` (stacked pre-scaled rows, lazy working set,
LAPACK factor of the Hessian handed to daqp as H = I); anything it cannot
settle falls back to the general `solve_jets`, which also drives recovery.

Recovery when a window QP is infeasible: first backtrack into already
committed jets and/or widen the window (re-solving earlier jets is allowed: the
trajectory is not flown during planning), then stretch the durations of the
segments around the failure by a bounded factor (later waypoint times shift by
the same amount), and only then report infeasibility with a diagnosis.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from planner_core.constraints import integrated_cost
from planner_core.jets import COSTS, ProblemCache, initial_jets, solve_jets, trajectory_from_jets
from planner_core.problem import Bounds, FloatArray, Polytope, Problem
from planner_core.qp import BACKENDS
from planner_core.result import PlanResult, PlanStatus
from planner_core.window import WindowSolver, kernel_unavailable

__all__ = ["IterativeOptions", "plan_iterative", "solve_jets"]

DEFAULT_WINDOW = 6  # measured: median cost ~1.002x global on cluttered scenes, 1.01x at m=1000, ~10% slower per step than 4 (benchmarks/planner.py --quality)


@dataclass(frozen=True)
class IterativeOptions:
    window: int = DEFAULT_WINDOW  # jets solved per QP (1 = the paper's method)
    cost: str = "snap"  # "snap" | "jerk" | "waypoint-snap"
    backend: str = "daqp"  # "daqp" | "osqp"
    recover: bool = True
    # (backtrack, extra window) attempts, in order, before stretching durations
    retries: tuple[tuple[int, int], ...] = ((0, 1), (1, 0), (1, 1), (2, 2), (4, 2))
    stretch_factor: float = 1.5
    max_stretches: int = 4  # per failure site; total factor <= 1.5**4 ~ 5
    diagnose: bool = True
    # the compiled pass (window_kernel: block-tridiagonal Goldfarb-Idnani) settles the windows it
    # can; False leaves every window to WindowSolver.solve + daqp (the reference it is tested against)
    compiled: bool = True
    # False: a window the compiled pass cannot settle fails the plan at once, without the general
    # path (daqp, recovery, diagnosis). For searches that only need a quick yes/no (the
    # minimum-time allocation): "no" may then come where the general path would have planned.
    # Ignored where the compiled pass cannot run.
    fallback: bool = True

    def __post_init__(self) -> None:
        if self.window < 1:
            raise ValueError(f"window: must be >= 1, got {self.window}")
        if self.cost not in COSTS:
            raise ValueError(f"cost: unknown cost {self.cost!r} (expected one of {COSTS})")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend: unknown backend {self.backend!r} (expected one of {BACKENDS})")
        if self.stretch_factor <= 1.0:
            raise ValueError("stretch_factor: must be > 1")


@dataclass
class _Timers:
    build: list[float] = field(default_factory=list)
    solve: list[float] = field(default_factory=list)
    check: list[float] = field(default_factory=list)

    def add(self, times: tuple[float, float, float]) -> None:
        self.build.append(times[0])
        self.solve.append(times[1])
        self.check.append(times[2])

    def medians(self) -> dict[str, float]:
        return {
            f"step_{name}_median": float(np.median(v)) if v else 0.0
            for name, v in (("build", self.build), ("solve", self.solve), ("check", self.check))
        }


def _fast_solver(cache: ProblemCache, opts: IterativeOptions) -> WindowSolver | None:
    """The hot path covers the default configuration; other costs/backends take the general one."""
    if opts.backend != "daqp" or opts.cost not in ("snap", "jerk") or cache.problem.m < 3:
        return None
    return WindowSolver(cache, 4 if opts.cost == "snap" else 3)


def _stretch(problem: Problem, segments: list[int], factor: float) -> Problem:
    d = problem.durations.copy()
    d[segments] *= factor
    times = problem.times[0] + np.concatenate([[0.0], np.cumsum(d)])
    return replace(problem, times=times)


def _window(j: int, h: int, m: int) -> list[int]:
    return list(range(j, min(j + h, m - 1)))


def _try(
    problem: Problem,
    cache: ProblemCache,
    jets: FloatArray,
    j: int,
    h: int,
    back: int,
    opts: IterativeOptions,
    timers: _Timers | None = None,
    guess: FloatArray | None = None,
) -> FloatArray | None:
    start = max(1, j - back)
    free = list(range(start, min(j + h, problem.m - 1)))
    res = solve_jets(
        problem, jets, free, cost=opts.cost, backend=opts.backend, open_end=True, cache=cache, guess=guess
    )
    if timers is not None:
        timers.build.append(res.t_build)
        timers.solve.append(res.t_solve)
        timers.check.append(res.t_check)
    if not res.ok:
        return None
    if guess is not None:
        guess[free] = res.jets[free]  # the uncommitted part predicts the next window
    out = jets.copy()
    out[start : j + 1] = res.jets[start : j + 1]  # commit up to j only
    return out


def plan_iterative(problem: Problem, options: IterativeOptions | None = None) -> PlanResult:
    opts = options or IterativeOptions()
    t_start = time.perf_counter()
    m = problem.m
    cache = ProblemCache(problem)
    fast = _fast_solver(cache, opts)
    t_cache = time.perf_counter() - t_start
    jets = initial_jets(problem)
    timers = _Timers()
    guess = jets.copy()
    step_times = np.zeros(max(m - 2, 0))
    n_steps = 0
    recoveries: list[dict[str, Any]] = []
    stretched: dict[int, float] = {}
    original = problem
    j = 1
    kernel_steps = 0
    while j <= m - 2:
        if fast is not None and opts.compiled:
            # compiled pass: commits jets j.. until a window it cannot settle (or the end)
            times_j = np.zeros(m)
            j_stop = fast.run(jets, guess, j, opts.window, times_j)
            done = times_j[j:j_stop]
            take = min(done.size, step_times.size - n_steps)
            step_times[n_steps : n_steps + take] = done[:take]
            n_steps += take
            kernel_steps += j_stop - j
            j = j_stop
            if j > m - 2:
                break
            if not opts.fallback and kernel_unavailable() is None:
                stats = {"method": "iterative", "window": opts.window, "failed_waypoint": j,
                         "recoveries": recoveries, "time_total": time.perf_counter() - t_start,
                         "fallback": False}
                return PlanResult(PlanStatus.INFEASIBLE, None,
                                  f"infeasible at waypoint {j} (compiled pass only, fallback off)", None, stats)
        t0 = time.perf_counter()
        new: FloatArray | None = None
        if fast is not None and not opts.compiled:
            f1 = min(j + opts.window - 1, m - 2)
            d = fast.solve(jets, j, f1, True)
            if d is not None:
                guess[j : f1 + 1, 1:] = d  # for the general path, should it be needed next
                jets[j, 1:] = d[0]  # commit the jet at j only
                new = jets
                timers.add(fast.times)
        if new is None:
            new = _try(problem, cache, jets, j, opts.window, 0, opts, timers, guess)
        if n_steps < step_times.size:
            step_times[n_steps] = time.perf_counter() - t0
            n_steps += 1
        if new is None and opts.recover:
            new, problem, cache, info = _recover(problem, cache, jets, j, opts, stretched)
            recoveries.append(info)
            if fast is not None and fast.cache is not cache:
                fast = _fast_solver(cache, opts)  # durations were stretched
        if new is None:
            return _infeasible(problem, cache, jets, j, opts, t_start, recoveries)
        jets = new
        j += 1
    step_times = step_times[:n_steps]
    if m == 2:
        pass  # a single segment: both jets are given, nothing to solve
    ctrl_ok = _check_terminal_segment(problem, cache, jets, opts)
    if not ctrl_ok:
        return _infeasible(problem, cache, jets, max(1, m - 2), opts, t_start, recoveries)
    traj = trajectory_from_jets(problem, jets)
    stats = {
        "method": "iterative",
        "window": opts.window,
        "cost": opts.cost,
        "cost_note": _cost_note(opts.cost, opts.window),
        "backend": opts.backend,
        "integrated_snap": integrated_cost(traj.control_points, problem.durations, 4),
        "integrated_jerk": integrated_cost(traj.control_points, problem.durations, 3),
        "time_total": time.perf_counter() - t_start,
        "step_time_median": float(np.median(step_times)) if step_times.size else 0.0,
        "n_qp": int(step_times.size),
        "n_compiled_steps": kernel_steps,  # settled by window_kernel; the rest by the general path
        "compiled_unavailable": kernel_unavailable() if opts.compiled else "off (IterativeOptions.compiled)",
        "time_cache": t_cache,
        **timers.medians(),
        "recoveries": recoveries,
        "stretched_durations": _stretch_report(original, problem, stretched),
    }
    return PlanResult(PlanStatus.OK, replace(traj, stats=stats), "planned", None, stats)


def warm_up() -> str | None:
    """Compile the compiled pass now (or load it from numba's cache: ~20 s the first time on this
    machine, ~0.3 s after), so that no plan pays it. Returns why it cannot run here, else None."""
    eye = np.eye(3)
    wps = np.array([[0.0, 0.0, 0.0], [2.0, 1.0, 0.0], [4.0, 0.0, 1.0], [6.0, 1.0, 1.0]])
    box = Polytope(np.concatenate([eye, -eye]), np.full(6, 10.0))
    problem = Problem.from_waypoints(wps, np.full(3, 2.0), Bounds.symmetric(7.0, 6.5, 15.0, 60.0), (box,) * 3)
    plan_iterative(problem, IterativeOptions(window=2))
    return kernel_unavailable()


def _cost_note(cost: str, window: int) -> str:
    if cost == "waypoint-snap":
        return "squared snap at the committed waypoints (paper eq. 15) + 1e-6*|x|^2 regulariser (rank-deficient otherwise)"
    what = "snap" if cost == "snap" else "jerk"
    return f"integrated squared {what} over the segments fully determined by a window of {window} jet(s)"


def _stretch_report(original: Problem, problem: Problem, stretched: dict[int, float]) -> list[dict[str, float]]:
    return [
        {
            "segment": s,
            "old": float(original.durations[s]),
            "new": float(problem.durations[s]),
            "factor": float(problem.durations[s] / original.durations[s]),
        }
        for s in sorted(stretched)
    ]


def _recover(
    problem: Problem,
    cache: ProblemCache,
    jets: FloatArray,
    j: int,
    opts: IterativeOptions,
    stretched: dict[int, float],
) -> tuple[FloatArray | None, Problem, ProblemCache, dict[str, Any]]:
    info: dict[str, Any] = {"waypoint": j}
    for back, extra in opts.retries:
        new = _try(problem, cache, jets, j, opts.window + extra, back, opts)
        if new is not None:
            info.update(action="backtrack/widen", backtrack=back, window=opts.window + extra)
            return new, problem, cache, info
    if opts.max_stretches < 1:
        # nothing to stretch (local replans stretch on their own): skip the elastic LP, whose
        # answer would go unused, and its scipy import in the companion process
        info["action"] = "failed"
        return None, problem, cache, info
    from planner_core.diagnose import elastic_segments

    # stretch the segments whose constraints the elastic LP has to relax; else the whole window
    window = list(range(j - 1, min(j + opts.window, problem.m - 1)))
    segs = elastic_segments(problem, jets, _window(j, opts.window, problem.m), open_end=True, cache=cache)
    segs = [s for s in segs if s in window] or window
    for n in range(1, opts.max_stretches + 1):
        cand = _stretch(problem, segs, opts.stretch_factor**n)
        ccache = ProblemCache(cand)
        # segments before the failure keep their jets, but their durations are
        # unchanged, so committed jets stay valid; re-solve from j
        for back, extra in ((0, 0), *opts.retries):
            new = _try(cand, ccache, jets, j, opts.window + extra, back, opts)
            if new is not None:
                for s in segs:
                    stretched[s] = stretched.get(s, 1.0) * opts.stretch_factor**n
                info.update(action="stretch", segments=segs, factor=opts.stretch_factor**n,
                            backtrack=back, window=opts.window + extra)
                return new, cand, ccache, info
    info["action"] = "failed"
    return None, problem, cache, info


def _check_terminal_segment(problem: Problem, cache: ProblemCache, jets: FloatArray, opts: IterativeOptions) -> bool:
    """m == 2 has no QP; make sure its single segment is admissible (others were checked by their QP)."""
    if problem.m != 2:
        return True
    from planner_core.jets import CHECK_TOL

    sr = cache.rows(0)
    v = sr.rows @ np.concatenate([jets[0].ravel(), jets[1].ravel()])
    return bool(np.all(v <= sr.hi + CHECK_TOL) and np.all(v >= sr.lo - CHECK_TOL))


def _infeasible(
    problem: Problem,
    cache: ProblemCache,
    jets: FloatArray,
    j: int,
    opts: IterativeOptions,
    t_start: float,
    recoveries: list[dict[str, Any]],
) -> PlanResult:
    diag = None
    if opts.diagnose and problem.m > 2:
        from planner_core.diagnose import diagnose

        diag = diagnose(problem, jets, _window(j, opts.window, problem.m), open_end=True, cache=cache)
    msg = diag.message() if diag is not None else f"infeasible at waypoint {j}"
    stats = {
        "method": "iterative",
        "window": opts.window,
        "failed_waypoint": j,
        "recoveries": recoveries,
        "time_total": time.perf_counter() - t_start,
    }
    return PlanResult(PlanStatus.INFEASIBLE, None, msg, diag, stats)
