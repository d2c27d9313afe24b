"""`plan(problem, method, cost, **opts)`: one entry point, always verified."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from planner_core.feasibility import scale_search
from planner_core.iterative import IterativeOptions, plan_iterative
from planner_core.problem import ORDER_NAMES, Problem
from planner_core.result import Diagnosis, PlanResult, PlanStatus
from planner_core.verify import verify

if TYPE_CHECKING:
    from planner_core.separation import Neighbours

METHODS = ("iterative", "global")


def plan(problem: Problem, method: str = "iterative", cost: str | None = None, **opts: Any) -> PlanResult:
    """Plan a trajectory; the result is OK only if `verify` holds (1e-9 on every hull constraint).

    Options: iterative: window, backend, recover, diagnose (see IterativeOptions)
    or options=IterativeOptions(...); global: backend, diagnose.

    When the durations are infeasible, the iterative planner's `recover` (on by default)
    first stretches only the segments around each failing window (`iterative._recover_local`:
    O(window) a recovery, stats `recoveries`, `stretched_durations`), so a mission with a few
    tight segments never pays for the search below. Only when that fails (always for a
    single segment, which has no window) and `diagnose` is on (the default), a uniform
    duration-scale search (planner_core.feasibility, up to ~16 plans) finds the smallest scale
    that plans and the bound that binds first. With `recover` on, the plan at that scale is
    returned (stats `duration_scale`, `stretched_durations`); otherwise the INFEASIBLE
    result's diagnosis carries `binding`, `min_scale` and `min_durations`.

    `neighbours` (a `separation.Neighbours`, default none): other vehicles' committed
    trajectories to keep the separation from; see `_plan_against`.
    """
    neighbours = opts.pop("neighbours", None)
    if neighbours is not None and neighbours.trajectories:
        return _plan_against(problem, neighbours, method, cost, opts)
    if method == "iterative":
        base = opts.pop("options", None) or IterativeOptions()
        if cost is not None:
            opts["cost"] = cost
        iopts = replace(base, **opts)
        result = _plan_once(problem, method, cost, {"options": iopts})
        if result.ok or not iopts.diagnose:
            return result
        quiet = {"options": replace(iopts, recover=False, diagnose=False)}
        return _after_search(problem, result, lambda p: _plan_once(p, method, cost, dict(quiet)), iopts.recover)
    if method == "global":
        result = _plan_once(problem, method, cost, dict(opts))
        if result.ok or not opts.get("diagnose", True):
            return result
        quiet = {**opts, "diagnose": False}
        return _after_search(problem, result, lambda p: _plan_once(p, method, cost, dict(quiet)), False)
    raise ValueError(f"method: unknown method {method!r} (expected one of {METHODS})")


def _plan_against(problem: Problem, neighbours: Neighbours, method: str, cost: str | None,
                  opts: dict[str, Any]) -> PlanResult:
    """Plan keeping the separation from neighbours' committed trajectories (method.md, the fleet):
    first with one face per segment and neighbour (`_plan_faces`, any planner), and when that
    fails, with time-resolved rows (`_plan_rows`: a neighbour may cross our path within one of our
    segments at another time). OK only when every near neighbour's certificate holds."""
    coarse = _plan_faces(problem, neighbours, method, cost, opts)
    if coarse.ok:
        return coarse
    fine = _plan_rows(problem, neighbours, cost)
    if fine.ok:
        return fine
    stats = {**coarse.stats, "separation_rows": fine.stats.get("separation", {})}
    return replace(coarse, message=f"{coarse.message}; with time-resolved rows: {fine.message}", stats=stats)


ROW_ROUNDS = 3  # time-resolved rows: re-planes from the last plan, at most this many solves


def _plan_rows(problem: Problem, neighbours: Neighbours, cost: str | None) -> PlanResult:
    """All interior jets in one dense QP (the general jet solver) with the rows of
    `separation.planning_rows` (planes per common piece of our reference and each near
    neighbour). The reference is the given previous plan or the straight segments; when the
    solution is not certified, the planes are rebuilt from it (up to ROW_ROUNDS solves).
    Verified (`verify`, the rows, `certify_all`) like every plan."""
    from planner_core.jets import ProblemCache, initial_jets, solve_jets, trajectory_from_jets
    from planner_core.separation import certify_all, planning_rows, reference_trajectory

    t0 = time.perf_counter()
    nb = neighbours.for_bounds(problem.bounds)
    m = problem.m
    if m < 3:
        return PlanResult(PlanStatus.INFEASIBLE, None, "one segment is fixed by its end jets: nothing to move",
                          None, {"separation": {"ok": False}})
    ref = reference_trajectory(problem, nb.reference)
    jcost = cost if cost in ("snap", "jerk") else "snap"
    last = "no round ran"
    info: dict[str, Any] = {"ok": False, "rounds": 0}
    for rnd in range(ROW_ROUNDS):
        rows = planning_rows(problem.times, ref, nb)
        cache = ProblemCache(problem, extra_rows=rows)
        res = solve_jets(problem, initial_jets(problem), list(range(1, m - 1)), cost=jcost, backend="daqp", cache=cache)
        info.update(rounds=rnd + 1, rows=int(rows.rhs.size))
        if not res.ok:
            last = f"QP {res.status.value} with {rows.rhs.size} separation rows"
            break
        traj = trajectory_from_jets(problem, res.jets)
        report = verify(traj, problem)
        over = rows.violation(traj.control_points)
        if not report.ok or over > 1e-9:
            last = "verification failed: " + "; ".join(report.failures()) if not report.ok else f"rows violated by {over:.3g}"
            break
        certs, failure, near = certify_all(traj, nb)
        if failure is None:
            info.update(ok=True, near=near, neighbours=len(nb.trajectories), certificates=certs,
                        time_total=time.perf_counter() - t0)
            stats = {"method": "jets+separation rows", "cost": jcost, "separation": info, "verified": True,
                     "separation_rows": True}
            return PlanResult(PlanStatus.OK, replace(traj, stats=stats), "planned (time-resolved separation rows)",
                              None, stats)
        last = failure.message
        ref = traj  # planes again, from this plan
    info["time_total"] = time.perf_counter() - t0
    return PlanResult(PlanStatus.INFEASIBLE, None, last, None, {"separation": info})


def _plan_faces(problem: Problem, neighbours: Neighbours, method: str, cost: str | None,
                opts: dict[str, Any]) -> PlanResult:
    """Plan keeping the separation from neighbours with one face per segment and neighbour.

    Each segment's corridor is cut by one half-space per near neighbour (`separation.with_neighbours`:
    a plane fixed from our reference, linear in our control points, so the QP stays a QP), the
    cut problem is planned and verified as usual, and the result is then certified against every
    neighbour (`separation.certify_all`: a `SeparationCertificate` per near neighbour, the broad
    phase proves the far ones). OK only when every certificate holds. The trajectory keeps the
    problem's own corridors; the certificates are in stats["separation"]["certificates"] as
    (neighbour index, certificate). A recovery that stretches durations moves our plan in time
    against the faces: the certification then decides."""
    from planner_core.separation import certify_all, with_neighbours

    t0 = time.perf_counter()
    nb = neighbours.for_bounds(problem.bounds)
    cut, why = with_neighbours(problem, nb)
    t_faces = time.perf_counter() - t0
    if why is not None:
        stats: dict[str, Any] = {"separation": {"ok": False, "time_faces": t_faces}}
        return PlanResult(PlanStatus.INFEASIBLE, None, "separation: " + why, None, stats)
    result = plan(cut, method, cost, **opts)
    if result.ok and result.trajectory is not None and not np.array_equal(result.trajectory.times, problem.times):
        # recovery stretched durations: the faces were for the old times; once more at the new ones
        retimed = replace(problem, times=result.trajectory.times)
        cut, why = with_neighbours(retimed, nb)
        if why is not None:
            return PlanResult(PlanStatus.INFEASIBLE, None, "separation (after stretching durations): " + why, None,
                              {**result.stats, "separation": {"ok": False}})
        result = plan(cut, method, cost, **opts)
        if result.ok and result.trajectory is not None and not np.array_equal(result.trajectory.times, retimed.times):
            return PlanResult(PlanStatus.INFEASIBLE, None, "separation: the plan needs longer durations than the "
                              "neighbours' faces were built for", None, {**result.stats, "separation": {"ok": False}})
    if not result.ok or result.trajectory is None:
        return replace(result, message=result.message + " (against neighbours)")
    t1 = time.perf_counter()
    certs, failure, near = certify_all(result.trajectory, nb)
    info = {"ok": failure is None, "near": near, "neighbours": len(nb.trajectories), "certificates": certs,
            "time_faces": t_faces, "time_certify": time.perf_counter() - t1}
    stats = {**result.stats, "separation": info}
    if failure is not None:
        return PlanResult(PlanStatus.INFEASIBLE, None, "separation failed: " + failure.message, None, stats)
    traj = replace(result.trajectory, corridors=problem.corridors, stats=stats)
    return PlanResult(PlanStatus.OK, traj, result.message, None, stats)


def _after_search(problem: Problem, failed: PlanResult, plan_at: Callable[[Problem], PlanResult],
                  recover: bool) -> PlanResult:
    """Run the scale search after a failure: stretch (recover) or explain (see `plan`)."""
    t0 = time.perf_counter()
    found = scale_search(problem, plan_at)
    info = {**found.to_dict(), "time_scale_search": time.perf_counter() - t0}
    good = found.result
    if recover and found.scale is not None and good is not None and good.trajectory is not None:
        s = found.scale
        old, new = problem.durations, np.diff(good.trajectory.times)
        stretched = [{"segment": i, "old": float(old[i]), "new": float(new[i]), "factor": float(new[i] / old[i])}
                     for i in range(old.size)]
        stats = {**good.stats, "duration_scale": s, "stretched_durations": stretched, "scale_search": info,
                 "recoveries": [*failed.stats.get("recoveries", []), {"action": "uniform stretch", "factor": s}]}
        why = "" if found.binding is None else f" ({found.binding.describe()} binds first)"
        return PlanResult(PlanStatus.OK, replace(good.trajectory, stats=stats),
                          f"planned after stretching every duration by {s:.4g}x{why}", None, stats)
    diag = failed.diagnosis
    b = found.binding
    if diag is None:
        if b is not None and b.kind == "bounds" and b.order is not None:
            group = f"bounds order {b.order} ({ORDER_NAMES[b.order]}) of segment {b.segment}"
            diag = Diagnosis(b.segment + 1, b.segment, group, "bounds", b.order, (group,))
        elif b is not None:
            group = f"corridor of segment {b.segment}"
            diag = Diagnosis(b.segment + 1, b.segment, group, "corridor", None, (group,))
        else:
            w = int(failed.stats.get("failed_waypoint", 1))
            diag = Diagnosis(w, None, "no bound named", "unknown")
    min_d = None if found.scale is None else tuple(float(x) for x in found.scale * problem.durations)
    diag = replace(diag, binding=b, min_scale=found.scale, min_durations=min_d,
                   max_scale_tried=found.infeasible_below if found.scale is None else None)
    stats = {**failed.stats, "scale_search": info}
    message = diag.message() if failed.message.startswith("infeasible") else failed.message + "; " + diag.message()
    return PlanResult(PlanStatus.INFEASIBLE, None, message, diag, stats)


def _plan_once(problem: Problem, method: str, cost: str | None, opts: dict[str, Any]) -> PlanResult:
    """One plan, verified (no scale search)."""
    if method == "iterative":
        result = plan_iterative(problem, opts["options"])
    elif method == "global":
        from planner_core.global_qp import plan_global

        for key in opts:
            if key not in ("backend", "diagnose"):
                raise ValueError(f"{key}: not an option of the global planner (backend, diagnose)")
        result = plan_global(problem, cost=cost or "snap", **opts)
    else:
        raise ValueError(f"method: unknown method {method!r} (expected one of {METHODS})")
    if not result.ok or result.trajectory is None:
        return result
    t0 = time.perf_counter()
    # recovery may stretch durations: verify against the problem the trajectory solves
    checked = problem if result.trajectory.times.shape == problem.times.shape and (
        result.trajectory.times == problem.times).all() else replace(problem, times=result.trajectory.times)
    report = verify(result.trajectory, checked)
    stats = {**result.stats, "time_verify": time.perf_counter() - t0, "verified": report.ok}
    if not report.ok:
        return PlanResult(PlanStatus.INFEASIBLE, None, "verification failed: " + "; ".join(report.failures()),
                          None, stats)
    traj = replace(result.trajectory, stats=stats)
    return PlanResult(PlanStatus.OK, traj, result.message, None, stats)
