"""Planner result types (ruckig style: expected outcomes are result codes, not exceptions)."""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any

from planner_core.feasibility import Binding
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
    # from the duration-scale search (planner_core.feasibility), when it ran:
    binding: Binding | None = None  # the bound the plan at `min_scale` uses most of: binds first
    min_scale: float | None = None  # smallest uniform duration scale found to plan (None: none)
    max_scale_tried: float | None = None  # with min_scale None: the largest scale that failed
    min_durations: tuple[float, ...] | None = None  # the durations at min_scale

    def to_dict(self) -> dict[str, Any]:
        return {
            "waypoint": self.waypoint,
            "segment": self.segment,
            "group": self.group,
            "kind": self.kind,
            "order": self.order,
            "candidates": list(self.candidates),
            "binding": None if self.binding is None else self.binding.to_dict(),
            "min_scale": self.min_scale,
            "max_scale_tried": self.max_scale_tried,
            "min_durations": None if self.min_durations is None else list(self.min_durations),
        }

    def message(self) -> str:
        seg = "" if self.segment is None else f", segment {self.segment}"
        out = f"infeasible at waypoint {self.waypoint}{seg}: {self.group}"
        if self.min_scale is not None:
            out += f"; feasible from duration scale {self.min_scale:.4g}x"
            if self.min_durations is not None and len(self.min_durations) <= 8:
                out += " (durations " + ", ".join(f"{d:.4g}" for d in self.min_durations) + " s)"
            if self.binding is not None:
                out += f", where {self.binding.describe()} binds first"
        elif self.max_scale_tried is not None:
            out += f"; no uniform duration stretch up to {self.max_scale_tried:.3g}x plans it"
        return out


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
