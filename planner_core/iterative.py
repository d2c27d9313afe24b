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

Recovery when a window QP is infeasible, cheapest first. Local (`_recover_local`):
stretch the two segments at the window's sharpest turn, then the two at the
failing waypoint, then the whole window, by 1.5, 1.5^2, ... (later waypoint
times shift by the same amount), each tried with the compiled pass on a piece
of the mission around the failure (`_piece`: ~18 waypoints, their own cache and
solver), which also carries the pass on until the stretched segments are
behind it; then the whole-mission solver takes over again, its durations being
right from there on. So a recovery costs O(window), not O(m). Only if none of
that settles the window, on the whole mission (`_recover`, O(m)): backtrack
into already committed jets and/or widen the window (re-solving earlier jets
is allowed: the trajectory is not flown during planning), then stretch the
segments the elastic diagnosis picks; and only then is infeasibility reported
with a diagnosis (`planning.plan` then runs the uniform duration-scale search,
which a mission with a few tight segments therefore never pays).
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from planner_core.constraints import integrated_cost
from planner_core.jets import COSTS, ProblemCache, initial_jets, solve_jets, trajectory_from_jets
from planner_core.problem import Bounds, FloatArray, Polytope, Problem
from planner_core.qp import BACKENDS
from planner_core.result import PlanResult, PlanStatus
from planner_core.window import WindowSolver, kernel_kind, kernel_unavailable

__all__ = ["IterativeOptions", "compiled_pays_off", "plan_iterative", "solve_jets", "warm_up"]

LOCAL_SPAN = 16  # waypoints of a piece a local recovery re-plans, at least (see _piece)
RETRY_FIRST_WINDOW = 3  # windows up to this many jets try the retries before stretching (see _recover_local)
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


# Measured (benchmarks/footprint.py, crossover table): loading the compiled pass from numba's
# cache costs ~0.4-0.5 s (numba, LLVM and the cached code); it then saves ~0.2 ms a waypoint
# over the numpy + daqp path without recoveries, ~1 ms with the recoveries of cluttered scenes,
# so a process that plans once breaks even at ~300-2000 waypoints.
KERNEL_MIN_WAYPOINTS = 400


def compiled_pays_off(m: int) -> bool:
    """Whether one plan of m waypoints should use the compiled pass in this process: always once
    it is loaded; before that, only for problems big enough to repay loading it (a one-shot
    `python -m planner_core plan` of a small scenario is faster without numba). Loaded: numba's
    JIT build (`window_kernel`) or the AOT one (`planner_core.build_kernel`, ~ms to load)."""
    loaded = "planner_core.window_kernel" in sys.modules or "planner_core._window_aot" in sys.modules
    if loaded or m >= KERNEL_MIN_WAYPOINTS:
        return True
    from planner_core.window import aot_ready

    return aot_ready()  # milliseconds to load: it pays off at any size


def _fast_solver(cache: ProblemCache, opts: IterativeOptions) -> WindowSolver | None:
    """The hot path covers the default configuration; other costs/backends take the general one."""
    if opts.backend != "daqp" or opts.cost not in ("snap", "jerk") or cache.problem.m < 3:
        return None
    if opts.compiled:
        _compile_if_cold()
    return WindowSolver(cache, 4 if opts.cost == "snap" else 3)


_compile_checked: list[bool] = []


def _compile_if_cold() -> None:
    """The first plan after an install (or an edit of window_kernel.py) compiles the compiled
    pass, ~20 s here: say so before, and how long it took after, once per process (a warning
    on the `planner_core` logger: stderr unless the application configures logging)."""
    if _compile_checked:
        return
    _compile_checked.append(True)
    if kernel_kind() != "jit":  # none, or the AOT build: nothing to compile (nor numba to import)
        return
    from planner_core import window_kernel

    if window_kernel.cache_state() != "cold":
        return
    log = logging.getLogger("planner_core")
    log.warning("compiling the planner's kernel with numba (first use of this version: ~20-60 s, "
                "once; later processes load it from numba's cache in ~0.4 s) ...")
    t0 = time.perf_counter()
    warm_up()
    log.warning("compiled the planner's kernel in %.0f s", time.perf_counter() - t0)


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


@dataclass
class _Pass:
    """A solver over waypoints c0 .. c0 + problem.m - 1 of the mission (the whole of it, or a
    piece around a recovery), allowed to commit the jets of waypoints up to `limit`."""

    problem: Problem
    cache: ProblemCache
    fast: WindowSolver | None
    c0: int
    limit: int

    def view(self, arr: FloatArray) -> FloatArray:
        return arr[self.c0 : self.c0 + self.problem.m]


def _whole(problem: Problem, opts: IterativeOptions) -> _Pass:
    cache = ProblemCache(problem)
    return _Pass(problem, cache, _fast_solver(cache, opts), 0, problem.m - 2)


def _piece(problem: Problem, jets: FloatArray, j: int, opts: IterativeOptions, back: int = 1, widest: int = 0) -> _Pass:
    """The pass over the piece of `problem` around waypoint j that a local recovery works on.

    It starts at a committed jet before j - back (attempts on it re-solve from there) and
    reaches far enough that every window it commits sees only real waypoints: its far end
    stands in for the rest of the mission, so with windows of up to `widest` jets (default
    window + 1) it commits up to widest + 2 waypoints before it, and that limit lies past
    every segment a stretch of the window touches. Its problem, cache and solver cost
    O(window), not O(m).
    """
    m = problem.m
    h = opts.window
    widest = max(widest, h + 1)
    c0 = max(0, j - back - 1)
    c1 = min(m - 1, max(c0 + LOCAL_SPAN, j + h + widest + 2))
    final = problem.final if c1 == m - 1 else jets[c1]
    corridors = None if problem.corridors is None else problem.corridors[c0:c1]
    sub = Problem(problem.waypoints[c0 : c1 + 1], problem.times[c0 : c1 + 1], problem.bounds, jets[c0].copy(),
                  final.copy(), corridors)
    cache = ProblemCache(sub)
    limit = m - 2 if c1 == m - 1 else c1 - widest - 2
    return _Pass(sub, cache, _fast_solver(cache, opts), c0, limit)


def _solve_window(
    ps: _Pass, jets: FloatArray, guess: FloatArray, j: int, h: int, back: int, opts: IterativeOptions,
    timers: _Timers | None = None,
) -> bool:
    """Solve the window of h jets from waypoint j (back: re-solving that many committed ones too) on
    the pass `ps`; on success commit up to j into `jets` (global arrays) and return True."""
    m = ps.c0 + ps.problem.m  # global waypoints the pass reaches (+1)
    start = max(1, j - back)
    f1 = min(j + h, m - 1) - 1
    if ps.fast is not None:
        d = ps.fast.solve(ps.view(jets), start - ps.c0, f1 - ps.c0, True)
        if d is None:
            return False
        if timers is not None:
            timers.add(ps.fast.times)
        guess[start : f1 + 1, 1:] = d
        jets[start : j + 1, 1:] = d[: j + 1 - start]
        return True
    local = _try(ps.problem, ps.cache, ps.view(jets), j - ps.c0, h, back, opts, timers, ps.view(guess))
    if local is None:
        return False
    ps.view(jets)[:] = local
    return True


def _attempt(
    ps: _Pass, jets: FloatArray, guess: FloatArray, j0: int, j: int, h: int, window: int, opts: IterativeOptions
) -> int:
    """Settle waypoints j0 .. j on the pass `ps`; returns the first waypoint still to settle (at
    most j when j could not be). The compiled pass runs from j0 with windows of `window` jets
    and carries on as far as it can (up to the pass's limit); without it, one window of jets
    j0 .. j + h - 1 through `_solve_window`, committed up to j."""
    if ps.fast is not None and opts.compiled and kernel_unavailable() is None:
        times = np.zeros(ps.problem.m)
        j_stop = ps.fast.run(ps.view(jets), ps.view(guess), j0 - ps.c0, window, times) + ps.c0
        return min(j_stop, ps.limit + 1)
    return j + 1 if _solve_window(ps, jets, guess, j, h, j - j0, opts) else j


def _sharpest_turn(problem: Problem, j: int, window: list[int]) -> list[int]:
    """The two segments around the waypoint of the window (after j) whose turn asks the most
    acceleration for the time the durations give it: |v_out - v_in| / (mean duration) per axis,
    v from the straight legs, over the acceleration bound. Where a window looks ahead to a
    sharp turn, that turn, not waypoint j, is usually what needs more time."""
    w = problem.waypoints
    d = problem.durations
    inner = [k for k in range(window[0] + 1, window[-1] + 1) if k > j]
    if not inner:
        return []
    k = np.array(inner)
    v_in = (w[k] - w[k - 1]) / d[k - 1, None]
    v_out = (w[k + 1] - w[k]) / d[k, None]
    a = np.abs(v_out - v_in) / (0.5 * (d[k - 1] + d[k]))[:, None]
    lo_b, hi_b = problem.bounds.axis_limits()
    hi = np.maximum(hi_b[1], -lo_b[1])
    need = np.max(a / np.where(np.isfinite(hi) & (hi > 0), hi, np.inf), axis=1)
    worst = int(k[int(np.argmax(need))])
    return [worst - 1, worst]


def _recover_local(
    current: Problem, jets: FloatArray, guess: FloatArray, j: int, opts: IterativeOptions
) -> tuple[Problem, _Pass, dict[str, Any], int] | None:
    """Cheap recovery at waypoint j, on a piece of the mission around it (`_piece`), so that one
    costs O(window), not O(m): stretches, by stretch_factor^n, of the two segments at the
    window's sharpest turn, then of the two at waypoint j, then of every segment of the
    window. Returns the durations it chose, the piece (which carries the pass on), what it
    did and the next waypoint to settle; None if nothing settles j.

    Windows of up to RETRY_FIRST_WINDOW jets first try the retries (backtrack / widen) without
    stretching: on benchmarks/quality.py's scenes they settle most failures of windows of 1
    and 2 jets. Longer windows stretch at once: a wider window settled none of the 37
    failures of benchmarks/scale.py's 500/1000 scene (window 6), and each failed compiled
    attempt costs ~0.5-1 ms; their retries are left to the fallback (`_recover`). Measured
    on the scale scenes with the pair at j tried first (51 failures): the sharpest-turn pair
    settled 38, the pair at j 10, the whole window 3."""
    h = opts.window
    if h <= RETRY_FIRST_WINDOW:
        # a short window dead-ends where a longer look ahead would not: the retries first (each
        # as a compiled pass from j - back whose first window is the retry's joint window)
        most = max((b for b, _ in opts.retries), default=0)
        piece = _piece(current, jets, j, opts, back=most, widest=h + max((b + e for b, e in opts.retries), default=0))
        for back, extra in opts.retries:
            back = min(back, j - 1)
            nxt = _attempt(piece, jets, guess, j - back, j, h + extra, h + extra + back, opts)
            if nxt > j:
                return current, piece, {"action": "backtrack/widen", "backtrack": back, "window": h + extra,
                                        "local": True}, nxt
    m = current.m
    window = list(range(j - 1, min(j + h, m - 1)))
    choices: list[list[int]] = []
    for segs in (_sharpest_turn(current, j, window), [s for s in (j - 1, j) if s <= m - 2], window):
        if segs and segs not in choices:
            choices.append(segs)
    for n in range(1, opts.max_stretches + 1):
        factor = opts.stretch_factor**n
        for segs in choices:
            cand = _stretch(current, segs, factor)
            piece = _piece(cand, jets, j, opts)
            # segment j-1 is stretched: the rows that depend on its committed start jet alone
            # changed, and only a window in which that jet is free checks them (it re-solves it)
            nxt = _attempt(piece, jets, guess, max(1, j - 1), j, h, h, opts)
            if nxt > j:
                return cand, piece, {"action": "stretch", "segments": segs, "factor": factor, "local": True}, nxt
    return None


def plan_iterative(problem: Problem, options: IterativeOptions | None = None) -> PlanResult:
    opts = options or IterativeOptions()
    t_start = time.perf_counter()
    m = problem.m
    main = _whole(problem, opts)
    ps = main
    t_cache = time.perf_counter() - t_start
    jets = initial_jets(problem)
    timers = _Timers()
    guess = jets.copy()
    step_times = np.zeros(max(m - 2, 0))
    n_steps = 0
    recoveries: list[dict[str, Any]] = []
    stretched: dict[int, float] = {}
    original = problem
    current = problem  # durations as stretched so far
    j = 1
    kernel_steps = 0
    while j <= m - 2:
        if j > ps.limit:
            ps = main  # a piece hands back to the whole-mission solver (its durations hold from here on)
        if ps.fast is not None and opts.compiled:
            # compiled pass: commits jets j.. until a window it cannot settle (or the end)
            times_j = np.zeros(ps.problem.m)
            j_stop = ps.fast.run(ps.view(jets), ps.view(guess), j - ps.c0, opts.window, times_j) + ps.c0
            # a piece's commits past its limit saw its stand-in far end: they are redone
            j_stop = min(j_stop, ps.limit + 1)
            done = times_j[j - ps.c0 : j_stop - ps.c0]
            take = min(done.size, step_times.size - n_steps)
            step_times[n_steps : n_steps + take] = done[:take]
            n_steps += take
            kernel_steps += j_stop - j
            j = j_stop
            if j > ps.limit:
                continue
            if not opts.fallback and kernel_unavailable() is None:
                stats = {"method": "iterative", "window": opts.window, "failed_waypoint": j,
                         "recoveries": recoveries, "time_total": time.perf_counter() - t_start,
                         "fallback": False}
                return PlanResult(PlanStatus.INFEASIBLE, None,
                                  f"infeasible at waypoint {j} (compiled pass only, fallback off)", None, stats)
        t0 = time.perf_counter()
        j_next = j + 1
        # where the compiled pass ran and failed, the same QP is infeasible (or it would have been
        # settled): straight to recovery, whose last resort is the general path
        compiled_failed = ps.fast is not None and opts.compiled and kernel_unavailable() is None
        ok = ok_step = not compiled_failed and _solve_window(ps, jets, guess, j, opts.window, 0, opts, timers)
        if not ok and ps.fast is not None and not opts.compiled:
            # the reference configuration keeps its second opinion: the general path's QP
            local = _try(ps.problem, ps.cache, ps.view(jets), j - ps.c0, opts.window, 0, opts, timers, ps.view(guess))
            if local is not None:
                ps.view(jets)[:] = local
                ok = ok_step = True
        if n_steps < step_times.size:
            step_times[n_steps] = time.perf_counter() - t0
            n_steps += 1
        if not ok and opts.recover:
            t_rec = time.perf_counter()
            found = _recover_local(current, jets, guess, j, opts)
            if found is not None:
                current, ps, info, j_next = found
                info["waypoint"] = j
                kernel_steps += j_next - j - 1  # the attempt's compiled pass carried on past j
            else:
                # the elastic diagnosis and the general path on the whole mission (rare, O(m))
                cache = main.cache if main.problem is current else ProblemCache(current)
                new, cand, _, info = _recover(current, cache, jets, j, opts, stretched, first=compiled_failed)
                if new is not None:
                    jets[:] = new
                    if cand is not current:
                        current = cand
                        main = ps = _whole(current, opts)
            ok = info.get("action") != "failed"
            if ok and info.get("action") == "stretch" and info.get("local"):
                for sg in info["segments"]:
                    stretched[sg] = stretched.get(sg, 1.0) * float(info["factor"])
            info["time"] = time.perf_counter() - t_rec
            recoveries.append(info)
        if not ok:
            cache = main.cache if main.problem is current else ProblemCache(current)
            return _infeasible(current, cache, jets, j, opts, t_start, recoveries)
        j = j_next if not ok_step else j + 1
    step_times = step_times[:n_steps]
    problem = current
    ctrl_ok = _check_terminal_segment(problem, main.cache, jets, opts)
    if not ctrl_ok:
        return _infeasible(problem, main.cache, jets, max(1, m - 2), opts, t_start, recoveries)
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
    machine, ~0.4 s after; or load its AOT build, see `window.kernel_build`: ~ms), so that no
    plan pays it. Returns why it cannot run here, else None."""
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
    first: bool = False,
) -> tuple[FloatArray | None, Problem, ProblemCache, dict[str, Any]]:
    """first: also try the window as it is (the compiled pass's failure has not been checked by
    the general path yet)."""
    info: dict[str, Any] = {"waypoint": j}
    for back, extra in ((0, 0), *opts.retries) if first else opts.retries:
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
