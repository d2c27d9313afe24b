"""`python -m planner_core plan|verify ...` (exit codes: 0 ok, 1 verify failed, 2 bad input, 3 infeasible)."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from planner_core.errors import FieldError

EXIT_OK = 0
EXIT_VERIFY_FAILED = 1
EXIT_INVALID = 2
EXIT_INFEASIBLE = 3


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m planner_core", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)
    pl = sub.add_parser("plan", help="plan a scenario, write the trajectory JSON")
    pl.add_argument("scenario", type=Path)
    pl.add_argument("-o", "--output", type=Path, required=True)
    pl.add_argument("--method", choices=("iterative", "global"), default="iterative")
    pl.add_argument("--cost", choices=("snap", "jerk", "waypoint-snap"), default=None)
    pl.add_argument("--window", type=int, default=None, help="jets per QP (iterative; 1 = the paper)")
    pl.add_argument("--backend", choices=("daqp", "osqp"), default=None)
    pl.add_argument("--no-recover", action="store_true",
                    help="iterative: report the first infeasible QP instead of backtracking/stretching")
    pl.add_argument("--timing", choices=("default", "fastest"), default=None,
                    help="fastest: durations as short as the bounds allow (overrides the scenario's "
                         "times and its 'timing')")
    pl.add_argument("--plot", metavar="PREFIX", default=None, help="write PREFIX_path2d.png etc.")
    ve = sub.add_parser("verify", help="check a trajectory against a scenario")
    ve.add_argument("scenario", type=Path)
    ve.add_argument("trajectory", type=Path)
    ve.add_argument("--json", action="store_true", help="print the report as JSON")
    from planner_core.formats.replan_cli import (
        add_replan_parser,  # replan subcommand (planner_core/formats/replan_cli.py)
    )

    add_replan_parser(sub)
    return p


def _read_json(path: Path, what: str) -> Any:
    try:
        return json.loads(path.read_text())
    except OSError as e:
        raise InputError(what, f"cannot read {path}: {e.strerror}") from e
    except json.JSONDecodeError as e:
        raise InputError(what, f"{path}: invalid JSON ({e.msg} at line {e.lineno})") from e


class InputError(FieldError):
    """An input file that cannot be read or is not JSON; `.field` names which input."""


def _err(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr)


def _cmd_plan(args: argparse.Namespace) -> int:
    from planner_core.formats.io import ScenarioError, load_scenario, trajectory_to_dict
    from planner_core.planning import plan

    try:
        from planner_core.corridors import CorridorError
    except ImportError:  # pragma: no cover - corridors module always ships
        CorridorError = ValueError  # type: ignore[misc,assignment]

    try:
        scenario = load_scenario(_read_json(args.scenario, "scenario"))
    except (ScenarioError, InputError) as e:
        _err(f"invalid scenario: {e}")
        return EXIT_INVALID
    except CorridorError as e:
        _err(f"no safe corridor: {e}")
        return EXIT_INFEASIBLE
    opts: dict[str, Any] = {}
    if args.method == "iterative" and args.window is not None:
        if args.window < 1:
            _err("invalid option: --window: must be >= 1")
            return EXIT_INVALID
        opts["window"] = args.window
    if args.method == "iterative" and args.no_recover:
        opts["recover"] = False
    if args.backend is not None:
        opts["backend"] = args.backend
    if args.method == "global" and args.cost == "waypoint-snap":
        _err("invalid option: --cost: the global planner takes snap or jerk")
        return EXIT_INVALID
    timing = args.timing or scenario.timing
    fastest_note = ""
    if timing == "fastest":
        from planner_core.allocation import fastest_durations

        cost_opt = {} if args.cost is None else {"cost": args.cost}
        fast = fastest_durations(scenario.problem, args.method, **cost_opt, **opts)
        result = fast.result
        if fast.ok and result.trajectory is not None:
            t = result.trajectory
            fastest_note = (f"fastest timing: flight {t.t_end - t.t0:.4g} s over {t.n_segments} segment(s) "
                            f"({t.n_segments - scenario.problem.m + 1} knot(s) added), {fast.plans} verified "
                            f"candidate plans, {1e3 * fast.time:.1f} ms")
    else:
        result = plan(scenario.problem, args.method, args.cost, **opts)
    if not result.ok or result.trajectory is None:
        _err(result.message)
        if result.diagnosis is not None:
            print(json.dumps({"diagnosis": result.diagnosis.to_dict()}), file=sys.stderr)
        return EXIT_INFEASIBLE
    args.output.write_text(json.dumps(trajectory_to_dict(result.trajectory, scenario.frame), indent=1))
    st = result.stats
    if fastest_note:
        print(fastest_note)
    if "duration_scale" in st:  # the given durations were infeasible: say so, and what was flown
        print(f"note: the given durations are infeasible; {result.message}: durations "
              + ", ".join(f"{c['old']:.4g} -> {c['new']:.4g}" for c in st["stretched_durations"][:8])
              + (" ..." if len(st["stretched_durations"]) > 8 else "") + " s")
    print(
        f"planned {scenario.problem.m} waypoints ({args.method}): integrated snap "
        f"{st.get('integrated_snap', float('nan')):.6g}, {1e3 * st.get('time_total', 0.0):.2f} ms -> {args.output}"
    )
    if args.plot:
        try:
            from planner_core.formats.plot import plot_all
        except ImportError as e:  # matplotlib missing
            _err(f"plotting unavailable: {e}")
        else:
            for path in plot_all(result.trajectory, scenario, args.plot):
                print(f"wrote {path}")
    return EXIT_OK


def _cmd_verify(args: argparse.Namespace) -> int:
    from dataclasses import replace

    import numpy as np

    from planner_core.formats.io import ScenarioError, load_scenario, trajectory_from_dict
    from planner_core.verify import verify

    try:
        scenario = load_scenario(_read_json(args.scenario, "scenario"))
        traj = trajectory_from_dict(_read_json(args.trajectory, "trajectory"))
    except (ScenarioError, InputError) as e:
        _err(f"invalid input: {e}")
        return EXIT_INVALID
    except ValueError as e:  # CorridorError: the scenario itself cannot be flown
        _err(f"no safe corridor: {e}")
        return EXIT_INFEASIBLE
    problem = scenario.problem
    if traj.corridors is not None and problem.corridors is None:
        problem = replace(problem, corridors=traj.corridors)
    note = ""
    stretched = traj.stats.get("stretched_durations") if isinstance(traj.stats, dict) else None
    if stretched and traj.times.shape == problem.times.shape and not np.array_equal(traj.times, problem.times):
        # the planner's recovery lengthened some durations and says so in stats
        problem = replace(problem, times=traj.times)
        note = "note: checked against the trajectory's stretched times: " + json.dumps(stretched)
    alloc = traj.stats.get("allocation") if isinstance(traj.stats, dict) else None
    if isinstance(alloc, dict) and alloc.get("method") == "fastest":
        # planned with --timing fastest: its own durations, and knots on the given legs
        index = np.asarray(alloc.get("waypoint_index", []), dtype=np.int64)
        if traj.n_segments != problem.m - 1 and index.shape == (problem.m,) and np.all(np.diff(index) >= 1):
            from planner_core.allocation import insert_knots

            problem, _ = insert_knots(problem, np.diff(index))
        if traj.times.shape == problem.times.shape:
            problem = replace(problem, times=traj.times)
        note = f"note: checked against the trajectory's fastest timing ({traj.n_segments} segments)"
    report = verify(traj, problem)
    if note:
        print(note)
    print(json.dumps(report.to_dict(), indent=1) if args.json else report.summary())
    return EXIT_OK if report.ok else EXIT_VERIFY_FAILED


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "plan":
        return _cmd_plan(args)
    if args.command == "replan":
        from planner_core.formats.replan_cli import replan_command

        return replan_command(args)
    return _cmd_verify(args)
