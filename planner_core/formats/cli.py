"""`python -m planner_core plan|verify ...` (exit codes: 0 ok, 1 verify failed, 2 bad input, 3 infeasible).

`plan` reports the plan's own time apart from the process's start-up (imports, loading the
compiled pass); `--json` prints both as one JSON object. A one-shot plan of a small scenario
skips the compiled pass (numba): loading it costs more than it saves (`--compiled auto`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from planner_core.formats.cli_common import (
    EXIT_INFEASIBLE,
    EXIT_INVALID,
    EXIT_OK,
    EXIT_VERIFY_FAILED,
    InputError,
    err,
    read_json,
)


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
    pl.add_argument("--timing", choices=("auto", "default", "fastest"), default=None,
                    help="overrides the scenario's 'timing'. auto (the default): the scenario's times, or "
                         "the fastest the bounds allow when it has none; fastest: the fastest even when it "
                         "has times; default: its times, or the slower allocate_times when it has none")
    pl.add_argument("--time-weight", type=float, default=None, metavar="RHO",
                    help="choose the durations minimising J + RHO * T (integrated snap or jerk plus RHO "
                         "per second of flight; overrides the scenario's times, 'timing' and 'time_weight')")
    pl.add_argument("--plot", metavar="PREFIX", default=None, help="write PREFIX_path2d.png etc.")
    pl.add_argument("--compiled", choices=("auto", "on", "off"), default="auto",
                    help="the numba-compiled pass: auto = only for scenarios big enough to repay "
                         "loading it (~0.4 s; see planner_core.iterative.KERNEL_MIN_WAYPOINTS)")
    pl.add_argument("--json", action="store_true",
                    help="print a JSON summary (plan time, start-up, path) instead of the text line")
    ve = sub.add_parser("verify", help="check a trajectory against a scenario")
    ve.add_argument("scenario", type=Path)
    ve.add_argument("trajectory", type=Path)
    ve.add_argument("--json", action="store_true", help="print the report as JSON")
    from planner_core.formats.replan_cli import (
        add_replan_parser,  # replan subcommand (planner_core/formats/replan_cli.py)
    )

    add_replan_parser(sub)
    return p


def _cmd_plan(args: argparse.Namespace, started: float) -> int:
    from dataclasses import replace

    from planner_core.formats.io import ScenarioError, load_scenario, trajectory_json
    from planner_core.iterative import KERNEL_MIN_WAYPOINTS, compiled_pays_off, warm_up
    from planner_core.window import use_compiled_kernel

    try:
        from planner_core.geometry import CorridorError
    except ImportError:  # pragma: no cover - corridors module always ships
        CorridorError = ValueError  # type: ignore[misc,assignment]

    t_imported = time.perf_counter()
    try:
        scenario = load_scenario(read_json(args.scenario, "scenario"))
    except (ScenarioError, InputError) as e:
        err(f"invalid scenario: {e}")
        return EXIT_INVALID
    except CorridorError as e:
        err(f"no safe corridor: {e}")
        return EXIT_INFEASIBLE
    t_loaded = time.perf_counter()
    m = scenario.problem.m
    compiled = compiled_pays_off(m) if args.compiled == "auto" else args.compiled == "on"
    if compiled:
        unavailable = warm_up()  # loads (or, the first time, compiles) the compiled pass: start-up, not plan
        path = "compiled" if unavailable is None else f"numpy ({unavailable})"
    else:
        why = "--compiled off" if args.compiled == "off" else (
            f"{m} waypoints < {KERNEL_MIN_WAYPOINTS}: the numpy path is faster than loading numba")
        use_compiled_kernel(False, why)
        path = "numpy"
    t_ready = time.perf_counter()
    kernel_s = t_ready - t_loaded if compiled else 0.0
    startup: dict[str, Any] = {"imports_s": t_imported - started, "kernel_load_s": kernel_s,
                               "total_s": t_imported - started + kernel_s, "path": path}
    opts: dict[str, Any] = {}
    if args.method == "iterative" and args.window is not None:
        if args.window < 1:
            err("invalid option: --window: must be >= 1")
            return EXIT_INVALID
        opts["window"] = args.window
    if args.method == "iterative" and args.no_recover:
        opts["recover"] = False
    if args.backend is not None:
        opts["backend"] = args.backend
    if args.method == "global" and args.cost == "waypoint-snap":
        err("invalid option: --cost: the global planner takes snap or jerk")
        return EXIT_INVALID
    timing = args.timing or scenario.timing
    rho = args.time_weight if args.time_weight is not None else scenario.time_weight
    if rho is not None and not (rho > 0.0 and rho < float("inf")):
        err(f"invalid option: --time-weight: must be finite and > 0, got {rho}")
        return EXIT_INVALID
    from planner_core.missions import plan_mission

    problem = scenario.problem
    # "default" keeps the loader's allocate_times when the scenario has no times: the old behaviour
    durations = problem.durations if scenario.durations_given or timing == "default" else None
    if args.cost is not None:
        opts["cost"] = args.cost
    mission = plan_mission(problem.waypoints, problem.bounds, problem.corridors, durations, timing=timing,
                           time_weight=rho, initial=problem.initial, final=problem.final, t0=float(problem.times[0]),
                           method=args.method, **opts)
    result = mission.result
    chosen = "default" if timing == "default" and not scenario.durations_given else mission.timing
    fastest_note = _allocation_note(result, mission.timing, m, rho)
    plan_s = time.perf_counter() - t_ready  # planning and verifying, nothing of the start-up
    if not result.ok or result.trajectory is None:
        err(result.message)
        if result.diagnosis is not None:
            print(json.dumps({"diagnosis": result.diagnosis.to_dict()}), file=sys.stderr)
        return EXIT_INFEASIBLE
    st = result.stats
    timing = {"plan_s": plan_s, "scenario_s": t_loaded - t_imported, "startup": startup}
    written = replace(result.trajectory, stats={**st, **timing})  # the file says how long it all took, too
    # the user's waypoints among the segment boundaries (knots absent): replan counts in them
    t_write = time.perf_counter()
    args.output.write_text(trajectory_json(written, scenario.frame, mission.waypoint_index))
    timing["write_s"] = time.perf_counter() - t_write
    if args.json:
        print(json.dumps({"waypoints": m, "method": args.method, "output": str(args.output),
                          "integrated_snap": st.get("integrated_snap"), "planner_time_s": st.get("time_total"),
                          "fastest": fastest_note or None, "timing": chosen,
                          "allocation": st.get("allocation"), "duration_scale": st.get("duration_scale"),
                          **timing}))
        return EXIT_OK
    if fastest_note:
        print(fastest_note)
    if "duration_scale" in st:  # the given durations were infeasible: say so, and what was flown
        print(f"note: the given durations are infeasible; {result.message}: durations "
              + ", ".join(f"{c['old']:.4g} -> {c['new']:.4g}" for c in st["stretched_durations"][:8])
              + (" ..." if len(st["stretched_durations"]) > 8 else "") + " s")
    print(
        f"planned {m} waypoints ({args.method}, {path} path): integrated snap "
        f"{st.get('integrated_snap', float('nan')):.6g}, plan {1e3 * plan_s:.2f} ms -> {args.output}"
    )
    print(f"start-up {1e3 * startup['total_s']:.0f} ms (imports {1e3 * startup['imports_s']:.0f} ms, "
          f"compiled pass {1e3 * startup['kernel_load_s']:.0f} ms); scenario and corridors "
          f"{1e3 * timing['scenario_s']:.0f} ms; writing {1e3 * timing['write_s']:.0f} ms")
    if args.plot:
        try:
            from planner_core.formats.plot import plot_all
        except ImportError as e:  # matplotlib missing
            err(f"plotting unavailable: {e}")
        else:
            for path in plot_all(result.trajectory, scenario, args.plot):
                print(f"wrote {path}")
    return EXIT_OK


def _allocation_note(result: Any, mode: str, m: int, rho: float | None) -> str:
    """One line on how the durations were chosen (empty when they were the scenario's)."""
    a = result.stats.get("allocation") if result.ok else None
    if not isinstance(a, dict) or result.trajectory is None:
        return ""
    t = result.trajectory
    if mode == "time-weight":
        return (f"time weight {rho:g}: flight {a['flight']:.4g} s (fastest {a['fastest_flight']:.4g} s), "
                f"objective {a['objective']:.6g}, {a['plans']} verified candidate plans, {1e3 * a['time']:.1f} ms")
    how = ("duration search and local pass" if a.get("strategy") == "search" else
           "local pass only: more waypoints than the duration search is worth")
    return (f"fastest timing: flight {t.t_end - t.t0:.4g} s over {t.n_segments} segment(s) "
            f"({t.n_segments - m + 1} knot(s) added), {a['plans']} verified candidate plans, {1e3 * a['time']:.1f} ms "
            f"({how})")


def _cmd_verify(args: argparse.Namespace) -> int:
    from dataclasses import replace

    import numpy as np

    from planner_core.formats.io import ScenarioError, load_scenario, trajectory_from_dict
    from planner_core.verify import verify

    try:
        scenario = load_scenario(read_json(args.scenario, "scenario"))
        traj = trajectory_from_dict(read_json(args.trajectory, "trajectory"))
    except (ScenarioError, InputError) as e:
        err(f"invalid input: {e}")
        return EXIT_INVALID
    except ValueError as e:  # CorridorError: the scenario itself cannot be flown
        err(f"no safe corridor: {e}")
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
    if isinstance(alloc, dict) and alloc.get("method") in ("fastest", "time-weight"):
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


def main(argv: Sequence[str] | None = None, started: float | None = None) -> int:
    """`started`: perf_counter() at the process's entry (`python -m planner_core`), so that
    start-up counts the imports; else from this call."""
    t0 = time.perf_counter() if started is None else started
    args = _parser().parse_args(argv)
    if args.command == "plan":
        return _cmd_plan(args, t0)
    if args.command == "replan":
        from planner_core.formats.replan_cli import replan_command

        return replan_command(args)
    return _cmd_verify(args)
