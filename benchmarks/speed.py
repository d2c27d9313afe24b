"""How fast do plans fly against what the bounds allow (issue 12).

    python benchmarks/speed.py [--scenes 15] [--seed 0] [--json PATH]

Rows:
- single rest-to-rest legs of 1, 5, 20 and 50 m with the companion's default bounds
  (companion/config.py [planner.bounds]: v 3, a 3, j 10, s 50 per axis), along x;
- random cluttered missions (benchmarks/quality.py scenes: 6-13 waypoints, 8-25
  obstacles, corridors built from them) with the bounds replaced by v 5, a 5, j 15,
  s 60 per axis.

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

from planner_core import Bounds, Problem, Trajectory, allocate_times, plan, warm_up
from planner_core.bezier import end_map, hodograph_matrix, start_map, subdivision_matrix
from planner_core.feasibility import bound_usage

Row = dict[str, Any]
LEG_BOUNDS = Bounds.symmetric(3.0, 3.0, 10.0, 50.0)
MISSION_BOUNDS = Bounds.symmetric(5.0, 5.0, 15.0, 60.0)
LEGS = (1.0, 5.0, 20.0, 50.0)
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
    vmax = np.minimum(bounds.hi[0], -bounds.lo[0])
    return float(np.sum(np.max(np.abs(np.diff(waypoints, axis=0)) / vmax, axis=1)))


def peak_fractions(traj: Trajectory, problem: Problem) -> dict[str, float]:
    d = np.diff(traj.times)
    u = (np.arange(SAMPLES) + 0.5) / SAMPLES
    t = (traj.times[:-1, None] + d[:, None] * u[None, :]).ravel()
    sym = np.minimum(problem.bounds.hi, -problem.bounds.lo)
    out: dict[str, float] = {}
    for k, name in enumerate(("v", "a", "j", "s"), start=1):
        vals = np.abs(traj.evaluate(t, k))
        out[f"peak_{name}"] = float(np.max(vals / sym[k - 1]))
    up, dn = bound_usage(traj, problem)
    out["hull_v"] = float(max(up[:, 0].max(), dn[:, 0].max()))
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
    row: Row = {"kind": kind, "name": name, "alloc": how, "m": problem.m, "ok": bool(res.ok),
                "lower_bound": lb, "ruckig": ruck, "plan_ms": 1e3 * t_plan}
    if res.ok and res.trajectory is not None:
        traj = res.trajectory
        flight = traj.t_end - traj.t0
        row.update(flight=flight, vs_lb=flight / lb, vs_ruckig=None if ruck is None else flight / ruck,
                   **peak_fractions(traj, problem if problem.m == traj.n_segments + 1 else
                                    Problem(traj.waypoints, traj.times, problem.bounds, problem.initial,
                                            problem.final)))
        row["plans"] = traj.stats.get("allocation", {}).get("plans")
        row["segs"] = traj.n_segments
    return row


def legs(allocs: tuple[str, ...]) -> list[Row]:
    rows = []
    for length in LEGS:
        wps = np.array([[0.0, 0.0, 0.0], [length, 0.0, 0.0]])
        problem = Problem.from_waypoints(wps, np.diff(allocate_times(wps, LEG_BOUNDS)), LEG_BOUNDS)
        ruck = ruckig_time(length, LEG_BOUNDS)
        for how in allocs:
            res, t, _ = plan_timed(problem, how)
            rows.append(_row("leg", f"{length:g} m", how, problem, res, t, axis_lower_bound(wps, LEG_BOUNDS), ruck))
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
              and r["name"] != "1 m"]
        ms = [r["vs_lb"] for r in rows if r["kind"] == "mission" and r["alloc"] == how and r.get("vs_lb")]
        n_ms = sum(1 for r in rows if r["kind"] == "mission" and r["alloc"] == how)
        ok = sum(1 for r in rows if r["kind"] == "mission" and r["alloc"] == how and r["ok"])
        pt = [r["plan_ms"] for r in rows if r["kind"] == "mission" and r["alloc"] == how and r["m"] == 10]
        out.append(
            f"{how}: legs 5-50 m flight / ruckig {min(lg, default=float('nan')):.2f}-"
            f"{max(lg, default=float('nan')):.2f}x (target <= 1.25); missions median flight / per-axis "
            f"lower bound {float(np.median(ms)) if ms else float('nan'):.2f}x (target <= 1.5), {ok}/{n_ms} planned"
            + (f"; 10-waypoint plan time median {float(np.median(pt)):.1f} ms (target <= 50)" if pt else "")
        )
    return out


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
    descent x0.8/0.9/0.95/0.97) with 1 and 4 pieces, as flight / per-axis lower bound."""
    from dataclasses import replace

    from quality import random_scenario  # type: ignore[import-not-found]

    from planner_core.timing import durations_from_lengths

    rows = []
    for i in range(n):
        p = replace(random_scenario(seed + i).problem, bounds=MISSION_BOUNDS)
        base = durations_from_lengths(p.waypoints, MISSION_BOUNDS, safety=1.0, corridors=p.corridors)
        lb = axis_lower_bound(p.waypoints, MISSION_BOUNDS)
        row: Row = {"name": f"s{seed + i}", "m": p.m}
        for pc in (1, 4):
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
    potential: list[Row] = []
    if args.subdivision:
        potential = subdivision_potential(args.subdivision, args.seed)
        print("\nsubdivided certificate, potential (global feasibility LP, flight / per-axis lower bound):")
        for r in potential:
            print("  " + "  ".join(f"{k} {_fmt(v)}" for k, v in r.items()))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"rows": rows, "summary": summary(rows), "subdivision": potential},
                                        indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
