"""Solving a local replan (`planner_core.replan`): the free jets in one QP over the segments they
touch (`solve_derivatives`), or the iterative pass for a long run, or the general jet solver on a
window sub-problem (other costs, time-resolved separation rows); the new segments assembled and
certified; `search` widens the free set and stretches durations until one certifies.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np

from planner_core.certificate import certify_rebuilt, segment_ctrl, start_jet_of
from planner_core.localqp import solve_derivatives
from planner_core.problem import FloatArray, Polytope, Problem, Trajectory
from planner_core.replan_work import TIME_EPS, Infeasible, ReplanOptions, ReplanWork

if TYPE_CHECKING:
    from planner_core.separation import Neighbours

CONTINUITY_TOL = 1e-6  # relative, as verify.py
JOINT_MAX = 6  # free jets solved in one dense QP; longer runs go through the iterative pass


def _segments_of(free: set[int], m: int) -> set[int]:
    return {s for j in free for s in (j - 1, j) if 0 <= s < m - 1}


def _widen(free: set[int], work: ReplanWork) -> set[int]:
    if not free:
        base = {j for s in work.rebuilt() for j in (s, s + 1)}
        return {j for j in base if work.free_ok(j)}
    return free | {n for j in free for n in (j - 1, j + 1) if work.free_ok(n)}


def _solve(work: ReplanWork, free: set[int], opts: ReplanOptions) -> tuple[dict[int, FloatArray], float]:
    """Jets for `free`: one QP over the segments they touch (O(len(free)), never O(m))."""
    if not free:
        return {}, 0.0
    segs = _segments_of(free, work.m)
    jets = {i: work.jet(i) for s in segs for i in (s, s + 1)}
    durations = {s: float(work.times[s + 1] - work.times[s]) for s in segs}
    corridors = work.corridors
    cut = _neighbour_cut(work, sorted(segs), opts)

    def corridor_of(s: int) -> Polytope | None:
        if s in cut:
            return cut[s]
        return None if corridors is None else corridors[s]

    if len(free) > JOINT_MAX and max(free) - min(free) + 1 == len(free):
        # a long run of free jets (a big append): the iterative pass, O(run), not one dense QP
        return _solve_iterative(work, free, opts, cut)
    if opts.cost != "snap":  # other costs: the core's general jet solver on a window sub-problem
        return _solve_general(work, free, opts, cut)
    t0 = time.perf_counter()
    sol = solve_derivatives(jets, durations, work.bounds, corridor_of, sorted(free), backend=opts.backend)
    if not sol.ok:
        raise Infeasible(sol.message)
    return sol.jets, time.perf_counter() - t0


def _neighbour_cut(work: ReplanWork, segs: list[int], opts: ReplanOptions) -> dict[int, Polytope | None]:
    """The corridors of the re-solved segments cut by their neighbour faces (empty: no neighbours)."""
    nb = opts.neighbours
    if nb is None or not segs:
        return {}
    from planner_core.separation import NoFace, add_faces, neighbour_faces, reference_points

    old = Trajectory(work.old_times, work.old_ctrl)
    straight = np.stack([work.wps[segs], work.wps[[s + 1 for s in segs]]], axis=1)  # (k, 2, 3)
    u = np.linspace(0.0, 1.0, 10)[None, :, None]
    lines = straight[:, :1] * (1.0 - u) + straight[:, 1:] * u  # (k, 10, 3)
    full = np.zeros((work.m - 1, 10, 3))
    full[segs] = lines
    ref = reference_points(work.times, full, old, segs)
    try:
        faces = neighbour_faces(work.times, ref, nb, segs, give_up=True)
    except NoFace as exc:
        raise Infeasible(f"separation: {exc}") from exc
    corridors = work.corridors
    return {s: add_faces(None if corridors is None else corridors[s], faces[s]) for s in faces}


def _solve_rows(work: ReplanWork, free: set[int], opts: ReplanOptions) -> tuple[dict[int, FloatArray], float]:
    """Jets for `free` with time-resolved separation rows (`separation.planning_rows`, planes per
    common piece of the current plan and each near neighbour) in the general jet solver: for a
    neighbour that crosses our path within one segment, at another time."""
    from planner_core.jets import ProblemCache, solve_jets
    from planner_core.separation import planning_rows, reference_trajectory

    nb = opts.neighbours
    if nb is None or not free:
        return {}, 0.0
    lo = min(free) - 1
    sub, jets = _sub_problem(work, lo, max(free) + 1)
    old = Trajectory(work.old_times, work.old_ctrl)
    covers = old.t0 <= sub.times[0] + TIME_EPS and old.t_end >= sub.times[-1] - TIME_EPS
    rows = planning_rows(sub.times, old if covers else reference_trajectory(sub, None), nb)
    t0 = time.perf_counter()
    res = solve_jets(sub, jets, [j - lo for j in sorted(free)], cost=opts.cost if opts.cost in ("snap", "jerk") else "snap",
                     backend=opts.backend, cache=ProblemCache(sub, extra_rows=rows))
    elapsed = time.perf_counter() - t0
    if not res.ok:
        raise Infeasible(f"QP {res.status.value} for jets {sorted(free)} with {rows.rhs.size} separation rows")
    return {j: res.jets[j - lo] for j in free}, elapsed


def _sub_problem(work: ReplanWork, lo: int, hi: int,
                 cut: dict[int, Polytope | None] | None = None) -> tuple[Problem, FloatArray]:
    """Waypoints lo..hi as a problem of their own, the end jets fixed to the current ones."""
    jets = np.stack([work.jet(i) for i in range(lo, hi + 1)])
    corr = None if work.corridors is None else tuple(work.corridors[lo:hi])
    if cut:
        base = corr if corr is not None else (None,) * (hi - lo)
        corr = tuple(cut.get(s, c) for s, c in zip(range(lo, hi), base, strict=True))
    return Problem(work.wps[lo : hi + 1], work.times[lo : hi + 1], work.bounds, jets[0], jets[-1], corr), jets


def _solve_iterative(work: ReplanWork, free: set[int], opts: ReplanOptions,
                     cut: dict[int, Polytope | None] | None = None) -> tuple[dict[int, FloatArray], float]:
    from planner_core.iterative import IterativeOptions, plan_iterative

    lo, hi = min(free) - 1, max(free) + 1
    sub, _ = _sub_problem(work, lo, hi, cut)
    t0 = time.perf_counter()
    # no stretching inside: replan's own stretch step keeps the later segments' times consistent
    res = plan_iterative(sub, IterativeOptions(cost=opts.cost, backend=opts.backend, max_stretches=0, diagnose=False))
    elapsed = time.perf_counter() - t0
    if not res.ok or res.trajectory is None or not np.array_equal(res.trajectory.times, sub.times):
        raise Infeasible(f"iterative pass over jets {min(free)}..{max(free)}: {res.message}")
    ctrl = res.trajectory.control_points
    d = np.diff(sub.times)
    return {j: start_jet_of(ctrl[j - lo], float(d[j - lo])) for j in free}, elapsed


def _solve_general(work: ReplanWork, free: set[int], opts: ReplanOptions,
                   cut: dict[int, Polytope | None] | None = None) -> tuple[dict[int, FloatArray], float]:
    from planner_core.jets import solve_jets

    lo = min(free) - 1
    sub, jets = _sub_problem(work, lo, max(free) + 1, cut)
    t0 = time.perf_counter()
    res = solve_jets(sub, jets, [j - lo for j in sorted(free)], cost=opts.cost, backend=opts.backend)
    elapsed = time.perf_counter() - t0
    if not res.ok:
        raise Infeasible(f"QP {res.status.value} for jets {sorted(free)}")
    return {j: res.jets[j - lo] for j in free}, elapsed


def _assemble(work: ReplanWork, solved: dict[int, FloatArray], free: set[int]) -> tuple[Trajectory, list[int]]:
    m = work.m
    rebuild = sorted(set(work.rebuilt()) | _segments_of(free, m))
    times = work.times
    if work.same_layout:  # a plain copy (memcpy) is much cheaper than a gather at large m
        ctrl = work.old_ctrl.copy()
    else:
        ctrl = np.empty((m - 1, 10, 3))
        keep = np.ones(m - 1, dtype=bool)
        keep[rebuild] = False
        ctrl[keep] = work.old_ctrl[work.src[keep]]
    for s in rebuild:
        j0 = solved[s] if s in solved else work.jet(s)
        j1 = solved[s + 1] if s + 1 in solved else work.jet(s + 1)
        ctrl[s] = segment_ctrl(j0, j1, float(times[s + 1] - times[s]))
    return Trajectory(times.copy(), ctrl, work.corridor_tuple()), rebuild


def _certify(traj: Trajectory, work: ReplanWork, rebuild: list[int]) -> str | None:
    """Hull certificate of the rebuilt segments and C^4 continuity with their neighbours."""
    return certify_rebuilt(
        traj.control_points, traj.times, rebuild, work.bounds, traj.corridors, work.initial, work.final,
        continuity_tol=CONTINUITY_TOL,
    )


# --- the search: seeds, widening, stretching ----------------------------------


def search(work: ReplanWork, opts: ReplanOptions, stats: dict[str, Any],
           rows_first: bool = False) -> tuple[Trajectory, set[int]]:
    """Seeds first; widen one neighbour per step; then stretch the touched durations."""
    attempts = 0
    last = ""
    checked = False
    for stretch in range(opts.max_stretch + 1):
        if stretch:
            if not work.stretch(opts.stretch_factor):
                break
            stats["stretched"] = stretch
        free = set(work.seeds)
        for widen in range(opts.max_widen + 1):
            attempts += 1
            order = ((True, False) if rows_first else (False, True)) if opts.neighbours is not None else (False,)
            for rows in order:
                # with neighbours: one face per segment first, then time-resolved rows
                try:
                    solved, qp_time = _solve_rows(work, free, opts) if rows else _solve(work, free, opts)
                    stats["qp_time_s"] += qp_time
                    traj, rebuild = _assemble(work, solved, free)
                    failure = _certify(traj, work, rebuild)
                    if failure is None and opts.neighbours is not None and rebuild:
                        failure = _certify_separation(traj, rebuild, opts.neighbours, stats)
                    if failure is None:
                        stats.update(attempts=attempts, widened=widen, rebuilt_segments=rebuild)
                        if rows:
                            stats["separation_rows"] = True
                        return traj, free
                    last = f"certificate failed: {failure}"
                except Infeasible as exc:
                    last = str(exc)
            if not checked:
                # A waypoint outside its corridor fails every attempt (the certificate checks
                # P^0 and P^9): name it now instead of widening and stretching in vain. Checked
                # only after a failure, off the success path; nothing has stretched yet, so the
                # touched segments are the edit's own.
                _check_waypoints_in_corridors(work)
                checked = True
            wider = _widen(free, work)
            if wider == free:
                break
            free = wider
    raise Infeasible(
        f"no feasible local replan after {attempts} attempts (widening up to {opts.max_widen}, "
        f"stretching up to {opts.max_stretch}x): {last}",
        {"kind": "replan", "seeds": sorted(work.seeds), "attempts": attempts},
    )


def _certify_separation(traj: Trajectory, rebuild: list[int], nb: Neighbours, stats: dict[str, Any]) -> str | None:
    """The rebuilt span of `traj` certified against every neighbour near it (kept segments were
    certified when they were planned); the certificates go to stats["separation"]."""
    from planner_core.separation import certify_all

    t0 = time.perf_counter()
    end = max(rebuild) + 1
    # the span reaches for ever when the rebuilt part is the end: the held last point stays reserved
    t_to = None if end >= traj.n_segments else float(traj.times[end])
    certs, failure, near = certify_all(traj, nb, float(traj.times[min(rebuild)]), t_to)
    stats["separation"] = {"ok": failure is None, "near": near, "neighbours": len(nb.trajectories),
                           "certificates": certs, "time_certify": time.perf_counter() - t0}
    return None if failure is None else f"separation: {failure.message}"


def _check_waypoints_in_corridors(work: ReplanWork) -> None:
    if work.corridors is None:
        return
    for s in work.rebuilt():
        poly = work.corridors[s]
        if poly is None or poly.A.shape[0] == 0:
            continue
        over = (work.wps[s : s + 2] @ poly.A.T - poly.b).max(axis=1)  # both ends at once
        for i, v in zip((s, s + 1), over.tolist(), strict=True):
            if v > 1e-9:
                raise Infeasible(
                    f"waypoint {i} at {work.wps[i].tolist()} is outside the corridor of segment {s} (by {v:.3g})",
                    {"kind": "corridor", "segment": s, "waypoint": i},
                )
