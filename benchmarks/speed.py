"""How fast do plans fly against what the bounds allow (issue 12).

    python benchmarks/speed.py [--scenes 15] [--seed 0] [--json PATH]

Rows:
- single rest-to-rest legs of 1, 5, 20 and 50 m with the companion's default bounds
  (companion/config.py [planner.bounds]: v 3, a 3, j 10, s 50 per axis), along x and along the
  diagonals (1, 1, 0) and (1, 1, 1) ("5 m xy", "5 m xyz"); ruckig's time is its time on the
  binding axis (the largest per-axis distance: every axis has the same bounds);
- random cluttered missions (benchmarks/quality.py scenes: 6-13 waypoints, 8-25
  obstacles, corridors built from them) with the bounds replaced by v 5, a 5, j 15,
  s 60 per axis.

Also: the certificate's conservatism on the rest-to-rest segment per number of de Casteljau
pieces (the planner certifies each hodograph on constraints.HULL_PIECES of them), the takeoff
climb (`allocation.takeoff_duration`) and the time weight (`allocation.weighted_durations`,
min J + rho T) on a few missions, and the fastest allocation's cost against the mission size
(`--scale`: benchmarks/scale.py scenes without their durations, 10 to 1000 waypoints).

`proven` is a proven lower bound for any curve within v, a, j (planner_core.flight_time_lower_bound:
per axis, the runs between turning points, each from a stop to a stop, under v/a and a/j);
`proven_x` = proven / per-axis bound: a mission whose `proven_x` exceeds 1.5 cannot be flown
within 1.5x the per-axis bound by any planner.

For each: the allocation (`default`: planner_core.timing.allocate_times, what a
scenario without times gets; `fastest`: planner_core.fastest_durations), our flight
time, ruckig's time-optimal jerk-limited time for the same v/a/j (legs only: ruckig
ignores snap, so it is a lower bound for us; PyPI `ruckig`, the bench extra), the
per-axis lower bound sum_j max_axis |dW_j| / v_max, the ratios, the peak fraction of
each bound actually used (dense sampling, 400 samples per segment; `hull` is the
certificate's use of the velocity bound) and the planning time (allocation + plan;
median of 3). Every plan is verified (`plan` runs `verify`); a failed plan is shown
as such.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from planner_core import (
    Bounds,
    Problem,
    Trajectory,
    allocate_times,
    flight_time_lower_bound,
    plan,
    warm_up,
)
from planner_core.bezier import end_map, hodograph_matrix, start_map, subdivision_matrix
from planner_core.constraints import HULL_PIECES, certified_points

Row = dict[str, Any]
LEG_BOUNDS = Bounds.symmetric(3.0, 3.0, 10.0, 50.0)
MISSION_BOUNDS = Bounds.symmetric(5.0, 5.0, 15.0, 60.0)
LEGS = (1.0, 5.0, 20.0, 50.0)
DIRECTIONS = {"": (1.0, 0.0, 0.0), " xy": (1.0, 1.0, 0.0), " xyz": (1.0, 1.0, 1.0)}
SAMPLES = 400


def ruckig_time(length: float, bounds: Bounds) -> float | None:
    """Time-optimal jerk-limited rest-to-rest time along one axis (None without ruckig)."""
    try:
        from ruckig import InputParameter, Result, Ruckig
        from ruckig import Trajectory as RTraj
    except ImportError:
        return None
    inp = InputParameter(1)
    inp.current_position, inp.target_position = [0.0], [length]
    inp.max_velocity = [float(bounds.hi[0, 0])]
    inp.max_acceleration = [float(bounds.hi[1, 0])]
    inp.max_jerk = [float(bounds.hi[2, 0])]
    out = RTraj(1)
    res = Ruckig(1).calculate(inp, out)
    return float(out.duration) if res in (Result.Working, Result.Finished) else None


def axis_lower_bound(waypoints: np.ndarray, bounds: Bounds) -> float:
    """The issue's per-axis bound sum_j max_axis |dW_j| / v_max (planner_core's `per_segment`)."""
    return flight_time_lower_bound(waypoints, bounds).per_segment


def proven_lower_bound(waypoints: np.ndarray, bounds: Bounds) -> float:
    """planner_core.flight_time_lower_bound: no curve within v, a, j through these waypoints from
    rest to rest is faster (per axis, the runs between turning points under v/a and a/j)."""
    return flight_time_lower_bound(waypoints, bounds).value


def peak_fractions(traj: Trajectory, problem: Problem) -> dict[str, float]:
    d = np.diff(traj.times)
    u = (np.arange(SAMPLES) + 0.5) / SAMPLES
    t = (traj.times[:-1, None] + d[:, None] * u[None, :]).ravel()
    sym = np.minimum(problem.bounds.hi, -problem.bounds.lo)
    out: dict[str, float] = {}
    for k, name in enumerate(("v", "a", "j", "s"), start=1):
        vals = np.abs(traj.evaluate(t, k))
        out[f"peak_{name}"] = float(np.max(vals / sym[k - 1]))
    # the certificate's use of the velocity bound: its certified points (HULL_PIECES pieces)
    cert = certified_points(traj.control_points, 1, d)
    out["hull_v"] = float(np.max(np.maximum(cert / sym[0], -cert / sym[0])))
    return out


def plan_timed(problem: Problem, how: str, repeats: int = 3) -> tuple[Any, float, Problem]:
    """Allocate (`default` keeps the problem's times) and plan; median wall time of `repeats`."""
    from planner_core import fastest_durations

    times: list[float] = []
    res: Any = None
    planned = problem
    for _ in range(repeats):
        t0 = time.perf_counter()
        if how == "fastest":
            fast = fastest_durations(problem)
            planned, res = fast.problem, fast.result
        else:
            res = plan(problem)
        times.append(time.perf_counter() - t0)
    return res, float(np.median(times)), planned


def _row(kind: str, name: str, how: str, problem: Problem, res: Any, t_plan: float, lb: float,
         ruck: float | None) -> Row:
    proven = proven_lower_bound(problem.waypoints, problem.bounds)
    row: Row = {"kind": kind, "name": name, "alloc": how, "m": problem.m, "ok": bool(res.ok),
                "lower_bound": lb, "proven": proven, "proven_x": proven / lb, "ruckig": ruck, "plan_ms": 1e3 * t_plan}
    if res.ok and res.trajectory is not None:
        traj = res.trajectory
        flight = traj.t_end - traj.t0
        row.update(flight=flight, vs_lb=flight / lb, vs_proven=flight / proven, vs_ruckig=None if ruck is None else flight / ruck,
                   **peak_fractions(traj, problem if problem.m == traj.n_segments + 1 else
                                    Problem(traj.waypoints, traj.times, problem.bounds, problem.initial,
                                            problem.final)))
        row["plans"] = traj.stats.get("allocation", {}).get("plans")
        row["segs"] = traj.n_segments
    return row


def leg_problem(length: float, direction: tuple[float, float, float] = (1.0, 0.0, 0.0)) -> Problem:
    """A rest-to-rest leg of `length` metres along `direction`, the companion's bounds, allocate_times."""
    u = np.asarray(direction, dtype=float)
    wps = np.stack([np.zeros(3), length * u / np.linalg.norm(u)])
    return Problem.from_waypoints(wps, np.diff(allocate_times(wps, LEG_BOUNDS)), LEG_BOUNDS)


def legs(allocs: tuple[str, ...]) -> list[Row]:
    rows = []
    for suffix, direction in DIRECTIONS.items():
        for length in LEGS:
            problem = leg_problem(length, direction)
            wps = problem.waypoints
            ruck = ruckig_time(float(np.max(np.abs(wps[1] - wps[0]))), LEG_BOUNDS)  # the binding axis
            for how in allocs:
                res, t, _ = plan_timed(problem, how)
                rows.append(_row("leg", f"{length:g} m{suffix}", how, problem, res, t,
                                 axis_lower_bound(wps, LEG_BOUNDS), ruck))
    return rows


def missions(n: int, seed: int, allocs: tuple[str, ...]) -> list[Row]:
    from dataclasses import replace

    from quality import random_scenario  # type: ignore[import-not-found]

    rows = []
    for i in range(n):
        sc = random_scenario(seed + i)
        p = sc.problem
        times = allocate_times(p.waypoints, MISSION_BOUNDS, corridors=p.corridors)
        problem = replace(p, times=times, bounds=MISSION_BOUNDS)
        lb = axis_lower_bound(problem.waypoints, MISSION_BOUNDS)
        for how in allocs:
            res, t, _ = plan_timed(problem, how)
            rows.append(_row("mission", sc.name, how, problem, res, t, lb, None))
    return rows


def _fmt(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "NO"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.0f}"
    return str(v)


COLS = ["kind", "name", "alloc", "m", "segs", "ok", "flight", "ruckig", "vs_ruckig", "lower_bound", "vs_lb",
        "proven", "proven_x", "vs_proven",
        "peak_v", "peak_a", "peak_j", "peak_s", "hull_v", "plan_ms", "plans"]


def table(rows: list[Row]) -> str:
    cells = [[_fmt(r.get(c)) for c in COLS] for r in rows]
    w = [max(len(c), *(len(x[i]) for x in cells)) for i, c in enumerate(COLS)]
    lines = ["  ".join(c.rjust(w[i]) for i, c in enumerate(COLS))]
    lines += ["  ".join(x[i].rjust(w[i]) for i in range(len(COLS))) for x in cells]
    return "\n".join(lines)


def summary(rows: list[Row]) -> list[str]:
    out = []
    for how in sorted({r["alloc"] for r in rows}):
        lg = [r["vs_ruckig"] for r in rows if r["kind"] == "leg" and r["alloc"] == how and r.get("vs_ruckig")
              and not r["name"].startswith("1 m")]
        ms = [r["vs_lb"] for r in rows if r["kind"] == "mission" and r["alloc"] == how and r.get("vs_lb")]
        mt = [r["vs_proven"] for r in rows if r["kind"] == "mission" and r["alloc"] == how and r.get("vs_proven")]
        px = [r["proven_x"] for r in rows if r["kind"] == "mission" and r["alloc"] == how]
        n_ms = sum(1 for r in rows if r["kind"] == "mission" and r["alloc"] == how)
        ok = sum(1 for r in rows if r["kind"] == "mission" and r["alloc"] == how and r["ok"])
        pt = [r["plan_ms"] for r in rows if r["kind"] == "mission" and r["alloc"] == how and r["m"] == 10]
        out.append(
            f"{how}: legs 5-50 m flight / ruckig {min(lg, default=float('nan')):.2f}-"
            f"{max(lg, default=float('nan')):.2f}x (target <= 1.25); missions median flight / per-axis "
            f"lower bound {float(np.median(ms)) if ms else float('nan'):.2f}x (target <= 1.5; "
            f"{float(np.median(mt)) if mt else float('nan'):.2f}x the proven bound, which is itself "
            f"{float(np.median(px)) if px else float('nan'):.2f}x the per-axis one in the median), {ok}/{n_ms} planned"
            + (f"; 10-waypoint plan time median {float(np.median(pt)):.1f} ms (target <= 50)" if pt else "")
        )
    return out


def conservatism(pieces: tuple[int, ...] = (1, 2, 3, 4, 6)) -> list[Row]:
    """Certificate / true peak of the rest-to-rest segment (the fixed curve of a single leg), per
    order, when each hodograph is certified on p de Casteljau pieces (the planner uses
    HULL_PIECES); rows per segment is 3 (26 p + 4) bound rows."""
    from planner_core.bezier import evaluate_segment, segment_from_jets, stacked_pieces
    from planner_core.problem import rest_jet

    ctrl = segment_from_jets(rest_jet(np.zeros(3)), rest_jet(np.array([1.0, 0.0, 0.0])), 1.0)
    u = np.linspace(0.0, 1.0, 20001)
    rows = []
    for p in pieces:
        row: Row = {"pieces": p, "planner": "*" if p == HULL_PIECES else "", "bound_rows": 3 * (26 * p + 4)}
        for k, name in enumerate(("v", "a", "j", "s"), start=1):
            true = float(np.abs(evaluate_segment(ctrl, 1.0, u, k)[:, 0]).max())
            cert = stacked_pieces(9 - k, p) @ (hodograph_matrix(k, 1.0) @ ctrl)
            row[name] = float(np.abs(cert[:, 0]).max()) / true
        rows.append(row)
    return rows


def time_weights(n: int, seed: int, weights: tuple[float, ...]) -> list[Row]:
    """`weighted_durations` (min J + rho T) on the first n missions: flight against the fastest
    allocation's, the objective after the scale search and after the per-segment refinement,
    the candidate plans after the fastest allocation's, and the time."""
    from dataclasses import replace

    from quality import random_scenario  # type: ignore[import-not-found]

    from planner_core.allocation import weighted_durations

    rows = []
    for i in range(n):
        sc = random_scenario(seed + i)
        p = sc.problem
        problem = replace(p, times=allocate_times(p.waypoints, MISSION_BOUNDS, corridors=p.corridors),
                          bounds=MISSION_BOUNDS)
        for rho in weights:
            w = weighted_durations(problem, rho)
            row: Row = {"name": sc.name, "rho": rho, "ok": w.ok}
            if w.ok:
                a = w.result.stats["allocation"]
                row.update(flight=a["flight"], fastest=a["fastest_flight"], snap=a["integrated_cost"],
                           objective=a["objective"], after_scale=a["objective_scale"], scale=a["scale"],
                           plans=a["plans"] - a["fastest_plans"], ms=1e3 * a["time"])
            rows.append(row)
    return rows


def takeoffs(heights: tuple[float, ...] = (1.0, 3.0, 10.0)) -> list[Row]:
    """`takeoff_duration` (one certified rest-to-rest climb) against ruckig, companion bounds."""
    from planner_core.allocation import takeoff_duration

    out = []
    for h in heights:
        t = takeoff_duration(h, LEG_BOUNDS)
        r = ruckig_time(h, LEG_BOUNDS)
        out.append({"height": h, "duration": t, "ruckig": r, "vs_ruckig": None if r is None else t / r})
    return out


SCALE_OBSTACLES = {10: 10, 30: 30, 100: 50, 300: 100, 1000: 200}  # benchmarks/scale.py-like densities


def scaling(sizes: tuple[int, ...], repeats: int = 3) -> list[Row]:
    """The fastest allocation's cost against m (benchmarks/scale.py scenes without their durations,
    corridors from their obstacles): the plan at allocate_times' durations (what a scenario
    without times got before), `fastest_durations` as it runs by default (`strategy`: the
    duration search up to allocation.SEARCH_MAX_WAYPOINTS waypoints, the local pass alone above)
    and, for comparison, with the search forced on (one run: it is the slow one)."""
    from scale import scene  # type: ignore[import-not-found]

    from planner_core import fastest_durations
    from planner_core.formats.io import load_scenario

    out = []
    for m in sizes:
        sc = scene(SCALE_OBSTACLES.get(m, max(10, m // 5)), m)
        del sc["durations"]
        problem = load_scenario(sc).problem  # times: allocate_times
        default, t_default, _ = plan_timed(problem, "default", repeats)
        times, fast = [], None
        for _ in range(repeats):
            t0 = time.perf_counter()
            fast = fastest_durations(problem)
            times.append(time.perf_counter() - t0)
        assert fast is not None
        t0 = time.perf_counter()
        searched = fastest_durations(problem, search=True)
        t_search = time.perf_counter() - t0
        row: Row = {"m": m, "obstacles": len(sc["obstacles"]), "plan_ms": 1e3 * t_default,
                    "fastest_ms": 1e3 * float(np.median(times)), "strategy": fast.strategy, "plans": fast.plans,
                    "search_ms": 1e3 * t_search, "ok": bool(default.ok and fast.ok)}
        row["x_plan"] = row["fastest_ms"] / row["plan_ms"]
        for name, res in (("default", default), ("fastest", fast.result), ("search", searched.result)):
            row[f"flight_{name}"] = res.trajectory.t_end - res.trajectory.t0 if res.ok and res.trajectory else None
        if row["flight_default"] and row["flight_fastest"]:
            row["vs_default"] = row["flight_fastest"] / row["flight_default"]
        out.append(row)
    return out


def _rows_table(rows: list[Row]) -> str:
    cols = list(dict.fromkeys(k for r in rows for k in r))
    cells = [[_fmt(r.get(c)) for c in cols] for r in rows]
    w = [max(len(c), *(len(x[i]) for x in cells)) for i, c in enumerate(cols)]
    lines = ["  ".join(c.rjust(w[i]) for i, c in enumerate(cols))]
    lines += ["  ".join(x[i].rjust(w[i]) for i in range(len(cols))) for x in cells]
    return "\n".join(lines)


def lp_feasible(problem: Problem, durations: np.ndarray, pieces: int) -> bool:
    """The global feasibility LP (all interior jets at once, HiGHS) with the bounds certified on
    `pieces` de Casteljau pieces of each hodograph and the corridors on the control points."""
    from scipy.optimize import linprog

    m = problem.m
    nv = (m - 2) * 12  # derivatives 1..4 x 3 axes per interior waypoint
    fixed = {0: problem.initial, m - 1: problem.final}
    lo, hi = problem.bounds.lo, problem.bounds.hi
    a_rows: list[np.ndarray] = []
    b_rows: list[np.ndarray] = []

    def affine(cmap: np.ndarray, j: int, c0: np.ndarray, c1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows (r, 3, nv) and constants (r, 3) of the ctrl-space rows cmap (r, 10) of segment j."""
        r = cmap.shape[0]
        g = np.zeros((r, 3, nv))
        c = np.zeros((r, 3))
        for w, mx in ((j, cmap @ c0), (j + 1, cmap @ c1)):
            if w in fixed:
                c += mx @ fixed[w]
                continue
            c += np.outer(mx[:, 0], problem.waypoints[w])
            for k in range(1, 5):
                for ax in range(3):
                    g[:, ax, (w - 1) * 12 + (k - 1) * 3 + ax] += mx[:, k]
        return g, c

    for j in range(m - 1):
        d = float(durations[j])
        c0 = np.zeros((10, 5))
        c0[:5] = start_map(d)
        c1 = np.zeros((10, 5))
        c1[5:] = end_map(d)
        for k in range(1, 5):
            sub = subdivision_matrix(9 - k, pieces).reshape(-1, 10 - k)
            g, c = affine(sub @ hodograph_matrix(k, d), j, c0, c1)
            for ax in range(3):
                if np.isfinite(hi[k - 1, ax]):
                    a_rows.append(g[:, ax])
                    b_rows.append(hi[k - 1, ax] - c[:, ax])
                if np.isfinite(lo[k - 1, ax]):
                    a_rows.append(-g[:, ax])
                    b_rows.append(c[:, ax] - lo[k - 1, ax])
        poly = problem.corridor(j)
        if poly is not None:
            g, c = affine(np.eye(10), j, c0, c1)
            for f in range(poly.A.shape[0]):
                a_rows.append(np.einsum("a,rav->rv", poly.A[f], g))
                b_rows.append(poly.b[f] - c @ poly.A[f])
    res = linprog(np.zeros(nv), A_ub=np.vstack(a_rows), b_ub=np.concatenate(b_rows) + 1e-9,
                  bounds=[(None, None)] * nv, method="highs")
    return bool(res.status == 0)


def lp_min_scale(problem: Problem, base: np.ndarray, pieces: int, lo: float = 0.2, hi: float = 3.0,
                 tol: float = 0.01) -> float | None:
    if not lp_feasible(problem, base * hi, pieces):
        return None
    while hi / lo > 1 + tol:
        mid = float(np.sqrt(lo * hi))
        if lp_feasible(problem, base * mid, pieces):
            hi = mid
        else:
            lo = mid
    return hi


def subdivision_potential(n: int, seed: int) -> list[Row]:
    """What a subdivided certificate in the QP could give on the missions: the global feasibility
    LP's shortest plan (uniform scale on the safety-1 durations, then per-segment coordinate
    descent x0.8/0.9/0.95/0.97) with 1 and HULL_PIECES pieces, as flight / per-axis lower bound."""
    from dataclasses import replace

    from quality import random_scenario  # type: ignore[import-not-found]

    from planner_core.timing import durations_from_lengths

    rows = []
    for i in range(n):
        p = replace(random_scenario(seed + i).problem, bounds=MISSION_BOUNDS)
        base = durations_from_lengths(p.waypoints, MISSION_BOUNDS, safety=1.0, corridors=p.corridors)
        lb = axis_lower_bound(p.waypoints, MISSION_BOUNDS)
        row: Row = {"name": f"s{seed + i}", "m": p.m}
        for pc in (1, HULL_PIECES):
            s = lp_min_scale(p, base, pc)
            if s is None:
                continue
            d = base * s
            row[f"uniform_p{pc}"] = float(d.sum() / lb)
            for f in (0.8, 0.9, 0.95, 0.97):
                for _ in range(3):
                    better = False
                    for seg in np.argsort(-d):
                        c = d.copy()
                        c[seg] *= f
                        if lp_feasible(p, c, pc):
                            d, better = c, True
                    if not better:
                        break
            row[f"refined_p{pc}"] = float(d.sum() / lb)
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=15)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--alloc", default="default,fastest", help="comma list of default, fastest")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--time-weights", default="1,10,100", help="comma list of rho for min J + rho T ('' for none)")
    ap.add_argument("--weight-scenes", type=int, default=5, help="missions for the time-weight table")
    ap.add_argument("--scale", default="10,30,100,1000",
                    help="comma list of mission sizes for the fastest allocation's cost table ('' for none)")
    ap.add_argument("--subdivision", type=int, default=0, metavar="N",
                    help="also the subdivided-certificate potential on N missions (global LP, ~5 s each)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    allocs = tuple(a for a in args.alloc.split(",") if a)
    warm_up()
    if ruckig_time(1.0, LEG_BOUNDS) is None:
        print("note: ruckig is not installed (pip install ruckig): its column is empty")
    rows = legs(allocs) + missions(args.scenes, args.seed, allocs)
    print("legs: bounds v 3, a 3, j 10, s 50 (companion defaults); missions: v 5, a 5, j 15, s 60 per axis")
    print(table(rows))
    for line in summary(rows):
        print(line)
    cons = conservatism()
    print(f"\ncertificate / true peak on the rest-to-rest segment (planner: {HULL_PIECES} pieces per hodograph):")
    print(_rows_table(cons))
    lifts = takeoffs()
    print("\ntakeoff climb (takeoff_duration, companion bounds):")
    print(_rows_table(lifts))
    weights = tuple(float(x) for x in args.time_weights.split(",") if x)
    weighted = time_weights(args.weight_scenes, args.seed, weights) if weights else []
    if weighted:
        print("\ntime weight (min J + rho T; plans: candidates after the fastest allocation's):")
        print(_rows_table(weighted))
    sizes = tuple(int(x) for x in args.scale.split(",") if x)
    scaled_rows = scaling(sizes) if sizes else []
    if scaled_rows:
        print("\nfastest allocation against m (scale.py scenes without durations; x_plan = fastest_ms / plan_ms;"
              " search: the duration search forced on):")
        print(_rows_table(scaled_rows))
    potential: list[Row] = []
    if args.subdivision:
        potential = subdivision_potential(args.subdivision, args.seed)
        print("\nsubdivided certificate, potential (global feasibility LP, flight / per-axis lower bound):")
        for r in potential:
            print("  " + "  ".join(f"{k} {_fmt(v)}" for k, v in r.items()))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"rows": rows, "summary": summary(rows), "subdivision": potential,
                                         "conservatism": cons, "takeoff": lifts, "time_weight": weighted,
                                         "scaling": scaled_rows},
                                        indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
