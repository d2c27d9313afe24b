"""The public door of planner_core: everything a client (the companion) needs, by name.

Import from `planner_core` (which re-exports this module); the submodules are the
package's own business. Pure maths in, pure results out: no clocks, no sockets,
no files (the JSON codec below turns trajectories into dicts and back, nothing more).

- model: `Bounds`, `Polytope`, `Problem`, `Trajectory`, `FloatArray`, `rest_jet`
- results: `PlanResult`, `PlanStatus`, `Diagnosis`, `VerifyReport`, `ReplanResult`
- errors: `FieldError` (every field/reason input error) and its `ChangeError`, `CorridorError`
- a mission in one call: `plan_mission` -> `MissionPlan` (waypoints, bounds, corridors, optional
  durations and a timing mode in; the verified plan and the map back to the given waypoints out)
- planning: `plan`, `IterativeOptions`, `warm_up`; time allocation `allocate_times`,
  `durations_from_lengths`, `corridor_cap`, `DEFAULT_MIN_DURATION`; minimum-time allocation
  `fastest_durations` -> `FastestAllocation`, `weighted_durations` (min J + rho T), the
  takeoff climb's `takeoff_duration`; infeasibility help `Binding`, `ScaleSearch`,
  `scale_search`, `scaled_durations`; process-wide `use_compiled_kernel`
- certificate: `verify`, `verify_changed` (a local replan, checked only where it changed)
- the fleet: `certify_separation` -> `SeparationCheck` (status, first failing interval) carrying a
  `SeparationCertificate` (`certify_many`: one trajectory against many, batched); `verify_separation` (what a receiver runs); `common_pieces`,
  `speed_bound`; planning against other vehicles' committed trajectories: `Neighbours` (given to
  `plan(..., neighbours=...)` or `ReplanOptions(neighbours=...)`), `separation_rows` -> `SeparationRows`
- local replanning: `replan`, `Environment`, `ReplanOptions`, `ChangeSet` and the edits
  `MoveWaypoint`, `SetDuration`, `SetCorridor`, `AddObstacles`, `InsertWaypoint`,
  `RemoveWaypoint`, `AppendWaypoints`; `parse_change`, `parse_polytope`
- geometry: `build_corridors`, `polytope_vertices`, `first_hit`, `inflate`
- braking: `braking_trajectory`, `stop_time_scale`
- trajectory surgery: `split_at`, `splice`, `trim_before`, `shifted`, `held_still`, `hold`, `Sampler`, `sampler`,
  `start_jet`, `end_jet`, `split_segment`
- JSON: `trajectory_to_dict`, `trajectory_from_dict`, `trajectory_json` (the file's text, fast);
  bounds: `vehicle_bound` (one order's {"horizontal", "up", "down"} form), `bounds_to_dict`
  (the scenario's "bounds")
- user waypoint indices among knots: `WaypointMap`, `to_planned` -> `PlannedChange`
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from planner_core.allocation import (
        FastestAllocation,
        fastest_durations,
        takeoff_duration,
        weighted_durations,
    )
    from planner_core.bezier import segment_at, segments_at
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
    from planner_core.errors import FieldError
    from planner_core.feasibility import Binding, ScaleSearch, scale_search
    from planner_core.feasibility import scaled as scaled_durations
    from planner_core.formats.io import (
        bounds_to_dict,
        trajectory_from_dict,
        trajectory_json,
        trajectory_to_dict,
        vehicle_bound,
    )
    from planner_core.geometry import CorridorError, build_corridors, polytope_vertices
    from planner_core.indices import PlannedChange, WaypointMap, to_planned
    from planner_core.iterative import IterativeOptions, warm_up
    from planner_core.lower_bound import FlightTimeBound, flight_time_lower_bound
    from planner_core.missions import MissionPlan, plan_mission
    from planner_core.planning import plan
    from planner_core.problem import Bounds, FloatArray, Polytope, Problem, Trajectory, rest_jet
    from planner_core.replan import Environment, ReplanOptions, ReplanResult, replan
    from planner_core.result import Diagnosis, PlanResult, PlanStatus
    from planner_core.separation import (
        Neighbours,
        SeparationCertificate,
        SeparationCheck,
        SeparationRows,
        SeparationStatus,
        certify_all,
        certify_many,
        certify_separation,
        common_pieces,
        separation_rows,
        speed_bound,
        verify_separation,
    )
    from planner_core.timing import (
        DEFAULT_MIN_DURATION,
        allocate_times,
        corridor_cap,
        durations_from_lengths,
    )
    from planner_core.trajectory import (
        Sampler,
        end_jet,
        held_still,
        hold,
        sampler,
        shifted,
        splice,
        split_at,
        split_segment,
        start_jet,
        trim_before,
    )
    from planner_core.verify import VerifyReport, verify, verify_changed
    from planner_core.window import use_compiled_kernel

# Where each name lives. Nothing is imported until first asked for (PEP 562): a client that
# only loads a scenario does not pay for scipy's sparse matrices, the elastic LP or numba,
# and `python -m planner_core plan` starts in a fraction of the time.
_WHERE: dict[str, tuple[str, str]] = {
    "Neighbours": ("planner_core.separation", "Neighbours"),
    "SeparationCertificate": ("planner_core.separation", "SeparationCertificate"),
    "SeparationCheck": ("planner_core.separation", "SeparationCheck"),
    "SeparationRows": ("planner_core.separation", "SeparationRows"),
    "SeparationStatus": ("planner_core.separation", "SeparationStatus"),
    "certify_separation": ("planner_core.separation", "certify_separation"),
    "certify_all": ("planner_core.separation", "certify_all"),
    "certify_many": ("planner_core.separation", "certify_many"),
    "verify_separation": ("planner_core.separation", "verify_separation"),
    "separation_rows": ("planner_core.separation", "separation_rows"),
    "common_pieces": ("planner_core.separation", "common_pieces"),
    "speed_bound": ("planner_core.separation", "speed_bound"),
    "AddObstacles": ("planner_core.changes", "AddObstacles"),
    "allocate_times": ("planner_core.timing", "allocate_times"),
    "AppendWaypoints": ("planner_core.changes", "AppendWaypoints"),
    "Binding": ("planner_core.feasibility", "Binding"),
    "Bounds": ("planner_core.problem", "Bounds"),
    "braking_trajectory": ("planner_core.braking", "braking_trajectory"),
    "build_corridors": ("planner_core.geometry", "build_corridors"),
    "ChangeError": ("planner_core.changes", "ChangeError"),
    "ChangeSet": ("planner_core.changes", "ChangeSet"),
    "corridor_cap": ("planner_core.timing", "corridor_cap"),
    "CorridorError": ("planner_core.geometry", "CorridorError"),
    "DEFAULT_MIN_DURATION": ("planner_core.timing", "DEFAULT_MIN_DURATION"),
    "Diagnosis": ("planner_core.result", "Diagnosis"),
    "durations_from_lengths": ("planner_core.timing", "durations_from_lengths"),
    "end_jet": ("planner_core.trajectory", "end_jet"),
    "Environment": ("planner_core.replan", "Environment"),
    "fastest_durations": ("planner_core.allocation", "fastest_durations"),
    "FastestAllocation": ("planner_core.allocation", "FastestAllocation"),
    "takeoff_duration": ("planner_core.allocation", "takeoff_duration"),
    "weighted_durations": ("planner_core.allocation", "weighted_durations"),
    "FieldError": ("planner_core.errors", "FieldError"),
    "first_hit": ("planner_core.collision", "first_hit"),
    "flight_time_lower_bound": ("planner_core.lower_bound", "flight_time_lower_bound"),
    "FlightTimeBound": ("planner_core.lower_bound", "FlightTimeBound"),
    "FloatArray": ("planner_core.problem", "FloatArray"),
    "hold": ("planner_core.trajectory", "hold"),
    "inflate": ("planner_core.collision", "inflate"),
    "InsertWaypoint": ("planner_core.changes", "InsertWaypoint"),
    "IterativeOptions": ("planner_core.iterative", "IterativeOptions"),
    "MissionPlan": ("planner_core.missions", "MissionPlan"),
    "MoveWaypoint": ("planner_core.changes", "MoveWaypoint"),
    "parse_change": ("planner_core.changes", "parse_change"),
    "parse_polytope": ("planner_core.changes", "parse_polytope"),
    "plan": ("planner_core.planning", "plan"),
    "plan_mission": ("planner_core.missions", "plan_mission"),
    "PlanResult": ("planner_core.result", "PlanResult"),
    "PlanStatus": ("planner_core.result", "PlanStatus"),
    "Polytope": ("planner_core.problem", "Polytope"),
    "polytope_vertices": ("planner_core.geometry", "polytope_vertices"),
    "Problem": ("planner_core.problem", "Problem"),
    "RemoveWaypoint": ("planner_core.changes", "RemoveWaypoint"),
    "replan": ("planner_core.replan", "replan"),
    "ReplanOptions": ("planner_core.replan", "ReplanOptions"),
    "ReplanResult": ("planner_core.replan", "ReplanResult"),
    "rest_jet": ("planner_core.problem", "rest_jet"),
    "Sampler": ("planner_core.trajectory", "Sampler"),
    "segment_at": ("planner_core.bezier", "segment_at"),
    "segments_at": ("planner_core.bezier", "segments_at"),
    "sampler": ("planner_core.trajectory", "sampler"),
    "scale_search": ("planner_core.feasibility", "scale_search"),
    "scaled_durations": ("planner_core.feasibility", "scaled"),
    "ScaleSearch": ("planner_core.feasibility", "ScaleSearch"),
    "SetCorridor": ("planner_core.changes", "SetCorridor"),
    "SetDuration": ("planner_core.changes", "SetDuration"),
    "shifted": ("planner_core.trajectory", "shifted"),
    "held_still": ("planner_core.trajectory", "held_still"),
    "splice": ("planner_core.trajectory", "splice"),
    "split_at": ("planner_core.trajectory", "split_at"),
    "split_segment": ("planner_core.trajectory", "split_segment"),
    "start_jet": ("planner_core.trajectory", "start_jet"),
    "stop_time_scale": ("planner_core.braking", "stop_time_scale"),
    "Trajectory": ("planner_core.problem", "Trajectory"),
    "trajectory_from_dict": ("planner_core.formats.io", "trajectory_from_dict"),
    "trajectory_json": ("planner_core.formats.io", "trajectory_json"),
    "trajectory_to_dict": ("planner_core.formats.io", "trajectory_to_dict"),
    "vehicle_bound": ("planner_core.formats.io", "vehicle_bound"),
    "bounds_to_dict": ("planner_core.formats.io", "bounds_to_dict"),
    "trim_before": ("planner_core.trajectory", "trim_before"),
    "use_compiled_kernel": ("planner_core.window", "use_compiled_kernel"),
    "verify": ("planner_core.verify", "verify"),
    "verify_changed": ("planner_core.verify", "verify_changed"),
    "VerifyReport": ("planner_core.verify", "VerifyReport"),
    "warm_up": ("planner_core.iterative", "warm_up"),
    "PlannedChange": ("planner_core.indices", "PlannedChange"),
    "to_planned": ("planner_core.indices", "to_planned"),
    "WaypointMap": ("planner_core.indices", "WaypointMap"),
}

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
    "FlightTimeBound",
    "FloatArray",
    "InsertWaypoint",
    "IterativeOptions",
    "MissionPlan",
    "MoveWaypoint",
    "Neighbours",
    "PlanResult",
    "PlanStatus",
    "PlannedChange",
    "Polytope",
    "Problem",
    "RemoveWaypoint",
    "ReplanOptions",
    "ReplanResult",
    "Sampler",
    "ScaleSearch",
    "SeparationCertificate",
    "SeparationCheck",
    "SeparationRows",
    "SeparationStatus",
    "SetCorridor",
    "SetDuration",
    "Trajectory",
    "VerifyReport",
    "WaypointMap",
    "allocate_times",
    "bounds_to_dict",
    "braking_trajectory",
    "build_corridors",
    "certify_all",
    "certify_many",
    "certify_separation",
    "common_pieces",
    "corridor_cap",
    "durations_from_lengths",
    "end_jet",
    "fastest_durations",
    "first_hit",
    "flight_time_lower_bound",
    "held_still",
    "hold",
    "inflate",
    "parse_change",
    "parse_polytope",
    "plan",
    "plan_mission",
    "polytope_vertices",
    "replan",
    "rest_jet",
    "sampler",
    "scale_search",
    "scaled_durations",
    "segment_at",
    "segments_at",
    "separation_rows",
    "shifted",
    "speed_bound",
    "splice",
    "split_at",
    "split_segment",
    "start_jet",
    "stop_time_scale",
    "takeoff_duration",
    "to_planned",
    "trajectory_from_dict",
    "trajectory_json",
    "trajectory_to_dict",
    "trim_before",
    "use_compiled_kernel",
    "vehicle_bound",
    "verify",
    "verify_changed",
    "verify_separation",
    "warm_up",
    "weighted_durations",
]


def __getattr__(name: str) -> Any:
    try:
        module, attr = _WHERE[name]
    except KeyError:
        raise AttributeError(f"module 'planner_core' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), attr)
    globals()[name] = value  # later look-ups are plain attribute reads
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
