"""The public door of planner_core: everything a client (the companion) needs, by name.

Import from `planner_core` (which re-exports this module); the submodules are the
package's own business. Pure maths in, pure results out: no clocks, no sockets,
no files (the JSON codec below turns trajectories into dicts and back, nothing more).

- model: `Bounds`, `Polytope`, `Problem`, `Trajectory`, `FloatArray`, `rest_jet`
- results: `PlanResult`, `PlanStatus`, `Diagnosis`, `VerifyReport`, `ReplanResult`
- errors: `FieldError` (every field/reason input error) and its `ChangeError`, `CorridorError`
- planning: `plan`, `IterativeOptions`, `warm_up`; time allocation `allocate_times`,
  `durations_from_lengths`, `corridor_cap`, `DEFAULT_MIN_DURATION`; minimum-time allocation
  `fastest_durations` -> `FastestAllocation`; infeasibility help `Binding`, `ScaleSearch`,
  `scale_search`, `scaled_durations`; process-wide
  `use_compiled_kernel` / `disable_kernel`
- certificate: `verify`, `verify_changed` (a local replan, checked only where it changed)
- local replanning: `replan`, `Environment`, `ReplanOptions`, `ChangeSet` and the edits
  `MoveWaypoint`, `SetDuration`, `SetCorridor`, `AddObstacles`, `InsertWaypoint`,
  `RemoveWaypoint`, `AppendWaypoints`; `parse_change`, `parse_polytope`
- geometry: `build_corridors`, `polytope_vertices`, `first_hit`, `inflate`
- braking: `braking_trajectory`, `stop_time_scale`
- trajectory surgery: `split_at`, `splice`, `trim_before`, `hold`, `Sampler`, `sampler`,
  `start_jet`, `end_jet`, `split_segment`
- JSON: `trajectory_to_dict`, `trajectory_from_dict`
"""

from __future__ import annotations

from planner_core.allocation import FastestAllocation, fastest_durations
from planner_core.braking import braking_trajectory, stop_time_scale
from planner_core.changes import (
    AddObstacles,
    AppendWaypoints,
    ChangeError,
    ChangeSet,
    InsertWaypoint,
    MoveWaypoint,
    RemoveWaypoint,
    SetCorridor,
    SetDuration,
    parse_change,
    parse_polytope,
)
from planner_core.collision import first_hit, inflate
from planner_core.corridors import CorridorError, build_corridors, polytope_vertices
from planner_core.errors import FieldError
from planner_core.feasibility import Binding, ScaleSearch, scale_search
from planner_core.feasibility import scaled as scaled_durations
from planner_core.formats.io import trajectory_from_dict, trajectory_to_dict
from planner_core.iterative import IterativeOptions, warm_up
from planner_core.planning import plan
from planner_core.problem import Bounds, FloatArray, Polytope, Problem, Trajectory, rest_jet
from planner_core.replan import Environment, ReplanOptions, ReplanResult, replan
from planner_core.result import Diagnosis, PlanResult, PlanStatus
from planner_core.timing import (
    DEFAULT_MIN_DURATION,
    allocate_times,
    corridor_cap,
    durations_from_lengths,
)
from planner_core.trajectory import (
    Sampler,
    end_jet,
    hold,
    sampler,
    splice,
    split_at,
    split_segment,
    start_jet,
    trim_before,
)
from planner_core.verify import VerifyReport, verify, verify_changed
from planner_core.window import disable_kernel, use_compiled_kernel

__all__ = [
    "DEFAULT_MIN_DURATION",
    "AddObstacles",
    "AppendWaypoints",
    "Binding",
    "Bounds",
    "ChangeError",
    "ChangeSet",
    "CorridorError",
    "Diagnosis",
    "Environment",
    "FastestAllocation",
    "FieldError",
    "FloatArray",
    "InsertWaypoint",
    "IterativeOptions",
    "MoveWaypoint",
    "PlanResult",
    "PlanStatus",
    "Polytope",
    "Problem",
    "RemoveWaypoint",
    "ReplanOptions",
    "ReplanResult",
    "Sampler",
    "ScaleSearch",
    "SetCorridor",
    "SetDuration",
    "Trajectory",
    "VerifyReport",
    "allocate_times",
    "braking_trajectory",
    "build_corridors",
    "corridor_cap",
    "disable_kernel",
    "durations_from_lengths",
    "end_jet",
    "fastest_durations",
    "first_hit",
    "hold",
    "inflate",
    "parse_change",
    "parse_polytope",
    "plan",
    "polytope_vertices",
    "replan",
    "rest_jet",
    "sampler",
    "scale_search",
    "scaled_durations",
    "splice",
    "split_at",
    "split_segment",
    "start_jet",
    "stop_time_scale",
    "trajectory_from_dict",
    "trajectory_to_dict",
    "trim_before",
    "use_compiled_kernel",
    "verify",
    "verify_changed",
    "warm_up",
]
