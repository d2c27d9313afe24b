"""The global planner (paper eq. 9): all interior jets in one sparse QP.

Same constraints as the iterative pass (every segment fully constrained),
cost = integrated squared snap (or jerk) over the whole trajectory. The
Hessian is block-tridiagonal in the jets; OSQP solves it, and `solve_qp`
refines OSQP's answer on its active set until the untightened rows hold to
1e-9 (checked in `solve_assembled`).
"""

from __future__ import annotations

import time
from dataclasses import replace

from planner_core.constraints import integrated_cost
from planner_core.jets import ProblemCache, initial_jets, solve_jets, trajectory_from_jets
from planner_core.problem import Problem
from planner_core.result import PlanResult, PlanStatus


def plan_global(problem: Problem, cost: str = "snap", backend: str = "osqp", diagnose: bool = True) -> PlanResult:
    if cost not in ("snap", "jerk"):
        raise ValueError(f"cost: the global planner takes 'snap' or 'jerk', got {cost!r}")
    t0 = time.perf_counter()
    m = problem.m
    cache = ProblemCache(problem)
    jets = initial_jets(problem)
    if m > 2:
        res = solve_jets(problem, jets, list(range(1, m - 1)), cost=cost, backend=backend, cache=cache)
        if not res.ok:
            diag = None
            if diagnose and m <= 60:  # one QP per group: only affordable on small problems
                from planner_core.diagnose import diagnose as run_diagnosis

                diag = run_diagnosis(problem, jets, list(range(1, m - 1)), cache=cache)
            msg = diag.message() if diag is not None else f"global QP {res.status.value}"
            return PlanResult(PlanStatus.INFEASIBLE, None, msg, diag,
                              {"method": "global", "time_total": time.perf_counter() - t0})
        jets = res.jets
    traj = trajectory_from_jets(problem, jets)
    stats = {
        "method": "global",
        "cost": cost,
        "cost_note": f"integrated squared {cost} over the whole trajectory",
        "backend": backend,
        "integrated_snap": integrated_cost(traj.control_points, problem.durations, 4),
        "integrated_jerk": integrated_cost(traj.control_points, problem.durations, 3),
        "time_total": time.perf_counter() - t0,
    }
    return PlanResult(PlanStatus.OK, replace(traj, stats=stats), "planned", None, stats)
