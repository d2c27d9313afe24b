"""`python -m planner_core replan SCENARIO.json TRAJ.json CHANGE.json -o NEW.json`.

Exit codes: 0 ok, 2 invalid input, 3 infeasible (no safe corridor, no local
replan, or the result failed the full certificate). The scenario supplies the
bounds and the environment (obstacles, map, radius) corridors are rebuilt
from; the trajectory supplies the current plan. When the trajectory no longer
matches the scenario's waypoints (it came from an earlier replan), the problem
is taken from the trajectory itself so that replans can be chained.

A change's indices count the user's waypoints: when the trajectory file has a
"waypoint_index" (the planner CLI writes it; knots are absent from it) they are
mapped onto the planned waypoints by `planner_core.indices.to_planned` (its
docstring has the rules for segments that hold knots), the new file gets the new
map, and messages and stats name user indices ("resolved_jets" the user waypoints
re-solved, "resolved_knots" how many knots were, "rebuilt_segments" user
segments; the planned indices under "planned"). A file without the map counts
every segment boundary as a waypoint, as before.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from planner_core.formats.cli_common import (
    EXIT_INFEASIBLE,
    EXIT_INVALID,
    EXIT_OK,
    InputError,
    err,
    read_json,
)
from planner_core.problem import Problem, Trajectory

if TYPE_CHECKING:
    from planner_core.indices import WaypointMap


def add_replan_parser(sub: Any) -> None:
    """Register the subcommand on an argparse subparsers object."""
    rp = sub.add_parser("replan", help="apply a change (CHANGE.json) to a planned trajectory locally")
    rp.add_argument("scenario", type=Path)
    rp.add_argument("trajectory", type=Path)
    rp.add_argument("change", type=Path)
    rp.add_argument("-o", "--output", type=Path, required=True)
    rp.add_argument("--max-widen", type=int, default=3, help="neighbour steps when the seed jets are infeasible")
    rp.add_argument("--max-stretch", type=int, default=2, help="duration stretches after widening fails")


def problem_for(scenario_problem: Problem, traj: Trajectory) -> Problem:
    """The scenario's problem if the trajectory still solves it, else the trajectory's own."""
    from planner_core.certificate import end_jet_of, start_jet_of

    same = (
        scenario_problem.m == traj.n_segments + 1
        and np.allclose(scenario_problem.waypoints, traj.waypoints, rtol=0.0, atol=1e-9)
        and np.allclose(scenario_problem.times, traj.times, rtol=0.0, atol=1e-9)
    )
    if same:
        corridors = scenario_problem.corridors if scenario_problem.corridors is not None else traj.corridors
        return Problem(
            scenario_problem.waypoints, scenario_problem.times, scenario_problem.bounds,
            scenario_problem.initial, scenario_problem.final, corridors,
        )
    d = np.diff(traj.times)
    return Problem(
        traj.waypoints, traj.times.copy(), scenario_problem.bounds,
        start_jet_of(traj.control_points[0], float(d[0])),
        end_jet_of(traj.control_points[-1], float(d[-1])),
        traj.corridors,
    )


def replan_command(args: argparse.Namespace) -> int:
    from planner_core.changes import ChangeError, parse_change
    from planner_core.formats.io import (
        ScenarioError,
        load_scenario,
        trajectory_from_dict,
        trajectory_json,
        waypoint_index_from_dict,
    )
    from planner_core.indices import WaypointMap, to_planned
    from planner_core.replan import Environment, ReplanOptions, replan
    from planner_core.verify import verify

    try:
        from planner_core.geometry import CorridorError
    except ImportError:  # pragma: no cover
        CorridorError = ValueError  # type: ignore[misc,assignment]

    try:
        raw_scenario = read_json(args.scenario, "scenario")
        raw_traj = read_json(args.trajectory, "trajectory")
        raw_change = read_json(args.change, "change")
    except InputError as e:
        err(f"invalid input: {e}")
        return EXIT_INVALID
    try:
        scenario = load_scenario(raw_scenario)
    except CorridorError as e:
        err(f"no safe corridor for the scenario: {e}")
        return EXIT_INFEASIBLE
    except ScenarioError as e:
        err(f"invalid scenario: {e}")
        return EXIT_INVALID
    try:
        traj = trajectory_from_dict(raw_traj)
        index = waypoint_index_from_dict(raw_traj)
    except ValueError as e:
        err(f"invalid trajectory: {e}")
        return EXIT_INVALID
    try:
        change = parse_change(raw_change)
    except ValueError as e:
        err(f"invalid change: {e}")
        return EXIT_INVALID
    if args.max_widen < 0 or args.max_stretch < 0:
        err("invalid option: --max-widen and --max-stretch must be >= 0")
        return EXIT_INVALID
    planned_m = traj.n_segments + 1
    wmap = WaypointMap.identity(planned_m) if index is None else WaypointMap(index, planned_m)
    problem = problem_for(scenario.problem, traj)
    env = Environment(tuple(scenario.obstacles), scenario.map_box, scenario.vehicle_radius)
    opts = ReplanOptions(max_widen=args.max_widen, max_stretch=args.max_stretch, environment=env)
    try:
        mapped = to_planned(change, wmap, problem.waypoints, traj.times)  # its errors are in user indices
    except ChangeError as e:
        err(f"invalid change: {e}")
        return EXIT_INVALID
    try:
        result = replan(problem, traj, mapped.change, options=opts)
    except ChangeError as e:  # the planned change's indices, told in the user's
        err(f"invalid change: {wmap.relabel_text(str(e))}")
        return EXIT_INVALID
    if not result.ok or result.trajectory is None:
        at = wmap.split_at(result.stats.get("split_index"))
        err(at.relabel_text(result.message))
        if result.diagnosis is not None:
            print(json.dumps({"diagnosis": at.relabel_diagnosis(result.diagnosis)}), file=sys.stderr)
        return EXIT_INFEASIBLE
    report = verify(result.trajectory, result.problem)
    if not report.ok:
        err(f"replanned trajectory failed the certificate: {report.summary()}")
        return EXIT_INFEASIBLE
    new_map = mapped.map_after(result.stats.get("split_index"), result.problem.m)
    message = new_map.relabel_text(result.message)
    stats = {**_user_stats(result.stats, list(result.resolved_jets), new_map, wmap), "message": message}
    out = Trajectory(result.trajectory.times, result.trajectory.control_points, result.trajectory.corridors, stats)
    args.output.write_text(trajectory_json(out, scenario.frame, new_map.index))
    knots = new_map.planned - new_map.n
    print(
        f"replanned: {message}; {new_map.n} waypoints" + (f" ({knots} knot(s) between them)" if knots else "")
        + f", {1e3 * float(result.stats.get('time_s', 0.0)):.2f} ms -> {args.output}"
    )
    return EXIT_OK


PLANNED_STATS = ("split_index", "lock", "rebuilt_segments")  # replan's stats that count planned waypoints


def _user_stats(
    stats: dict[str, Any], resolved: list[int], new_map: WaypointMap, old_map: WaypointMap
) -> dict[str, Any]:
    """replan's stats, with every index a user reads in user indices (module docstring)."""
    if new_map.is_identity and old_map.is_identity:
        return {**stats, "resolved_jets": resolved}
    users = [u for u in (new_map.user_of(j) for j in resolved) if u is not None]
    out = {k: v for k, v in stats.items() if k not in PLANNED_STATS}
    out["planned"] = {**{k: stats[k] for k in PLANNED_STATS if k in stats}, "resolved_jets": resolved}
    out["resolved_jets"] = users
    out["resolved_knots"] = len(resolved) - len(users)
    if "rebuilt_segments" in stats:
        out["rebuilt_segments"] = sorted({new_map.segment_of(int(s)) for s in stats["rebuilt_segments"]})
    return out
