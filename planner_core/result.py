"""Planner result types (ruckig style: expected outcomes are result codes, not exceptions)."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any

from planner_core.problem import Trajectory


class PlanStatus(enum.Enum):
    OK = "ok"
    INFEASIBLE = "infeasible"


@dataclass(frozen=True)
class Diagnosis:
    """Which constraint group made a QP infeasible (relax-and-check)."""

    waypoint: int  # the waypoint whose QP failed
    segment: int | None  # the segment of the blocking group
    group: str  # e.g. "bounds order 2 (acceleration) of segment 3"
    kind: str  # "bounds" | "corridor" | "initial" | "unknown"
    order: int | None = None
    candidates: tuple[str, ...] = ()  # every single group whose removal restores feasibility

    def to_dict(self) -> dict[str, Any]:
        return {
            "waypoint": self.waypoint,
            "segment": self.segment,
            "group": self.group,
            "kind": self.kind,
            "order": self.order,
            "candidates": list(self.candidates),
        }

    def message(self) -> str:
        seg = "" if self.segment is None else f", segment {self.segment}"
        return f"infeasible at waypoint {self.waypoint}{seg}: {self.group}"


@dataclass(frozen=True)
class PlanResult:
    status: PlanStatus
    trajectory: Trajectory | None
    message: str
    diagnosis: Diagnosis | None = None
    stats: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status is PlanStatus.OK and self.trajectory is not None
