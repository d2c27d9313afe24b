"""`plan(problem, method, cost, **opts)`: one entry point, always verified."""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

from planner_core.iterative import IterativeOptions, plan_iterative
from planner_core.problem import Problem
from planner_core.result import PlanResult, PlanStatus
from planner_core.verify import verify

METHODS = ("iterative", "global")


def plan(problem: Problem, method: str = "iterative", cost: str | None = None, **opts: Any) -> PlanResult:
    """Plan a trajectory; the result is OK only if `verify` holds (1e-9 on every hull constraint).

    Options: iterative: window, backend, recover, diagnose (see IterativeOptions)
    or options=IterativeOptions(...); global: backend, diagnose.
    """
    if method == "iterative":
        base = opts.pop("options", None) or IterativeOptions()
        if cost is not None:
            opts["cost"] = cost
        result = plan_iterative(problem, replace(base, **opts))
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
