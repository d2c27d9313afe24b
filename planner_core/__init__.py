"""Pure planning core: iterative Bernstein-polynomial QP planner (Strano, Furci, Marconi 2023)."""

from planner_core.iterative import IterativeOptions
from planner_core.planning import plan
from planner_core.problem import Bounds, Polytope, Problem, Trajectory
from planner_core.result import Diagnosis, PlanResult, PlanStatus
from planner_core.verify import VerifyReport, verify

__all__ = [
    "Bounds",
    "Diagnosis",
    "IterativeOptions",
    "PlanResult",
    "PlanStatus",
    "Polytope",
    "Problem",
    "Trajectory",
    "VerifyReport",
    "plan",
    "verify",
]
