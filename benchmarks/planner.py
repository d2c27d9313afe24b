"""Planner benchmark: iterative (per backend) vs global on random feasible problems.

    python benchmarks/planner.py [--sizes 10 100 1000] [--window H] [--json PATH]
    python benchmarks/planner.py --window-sweep     # cost / global for windows 1..5
    python benchmarks/planner.py --norm --sizes 100  # with a horizontal norm bound (docs/bounds.md)

Every function returns plain dict rows so other benchmarks can reuse them.
Timings are wall clock on whatever machine runs this; compare ratios, not
absolute numbers, when the machine is shared.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from planner_core import Bounds, IterativeOptions, Polytope, Problem, verify
from planner_core.global_qp import plan_global
from planner_core.iterative import DEFAULT_WINDOW, plan_iterative

Row = dict[str, Any]


def random_problem(m: int, seed: int = 0, pad: float = 1.0, norm: bool = False) -> Problem:
    """Random walk of waypoints, generous durations, a padded box corridor per segment; `norm`:
    a horizontal norm bound on velocity and acceleration too (5, 4.5: below the box's diagonal)."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=(m - 1, 3))
    steps[:, 2] *= 0.3
    steps *= rng.uniform(2.0, 5.0, size=(m - 1, 1)) / np.linalg.norm(steps, axis=1, keepdims=True)
    wps = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
    durations = np.linalg.norm(steps, axis=1) / 2.5 + 0.8
    eye = np.eye(3)
    cors = tuple(
        Polytope(
            np.concatenate([eye, -eye]),
            np.concatenate([np.maximum(wps[i], wps[i + 1]) + pad, -(np.minimum(wps[i], wps[i + 1]) - pad)]),
        )
        for i in range(m - 1)
    )
    bounds = Bounds.symmetric(7.0, 6.5, 15.0, 60.0)
    if norm:
        bounds = Bounds(bounds.lo, bounds.hi, horizontal=np.array([5.0, 4.5, np.inf, np.inf]))
    return Problem.from_waypoints(wps, durations, bounds, cors)


BACKEND_ROWS = {
    # label: (backend, compiled)
    "compiled": ("daqp", True),  # window_kernel (block-tridiagonal Goldfarb-Idnani), daqp for the rest
    "daqp": ("daqp", False),  # WindowSolver.solve: numpy rows, LAPACK factor, daqp per window
    "osqp": ("osqp", False),
}


def bench_iterative(problem: Problem, backend: str = "compiled", window: int = DEFAULT_WINDOW,
                    repeats: int | None = None) -> Row:
    """The plan with the median total time out of `repeats` (3 for the compiled pass: a
    planner process plans again and again; 1 for the slow paths)."""
    solver, compiled = BACKEND_ROWS[backend]
    n = repeats if repeats is not None else (3 if backend == "compiled" else 1)
    runs = [plan_iterative(problem, IterativeOptions(window=window, backend=solver, compiled=compiled))
            for _ in range(n)]
    res = sorted(runs, key=lambda r: float(r.stats.get("time_total", 0.0)))[n // 2]
    st = res.stats
    row: Row = {"method": "iterative", "backend": backend, "window": window, "m": problem.m, "ok": res.ok}
    if not res.ok or res.trajectory is None:
        return {**row, "message": res.message}
    t0 = time.perf_counter()
    rep = verify(res.trajectory, problem)
    t_verify = time.perf_counter() - t0
    return {
        **row,
        "verified": rep.ok,
        "time_total_ms": 1e3 * st["time_total"],
        "time_cache_ms": 1e3 * st["time_cache"],
        "step_median_us": 1e6 * st["step_time_median"],
        "step_build_us": 1e6 * st["step_build_median"],
        "step_solve_us": 1e6 * st["step_solve_median"],
        "step_check_us": 1e6 * st["step_check_median"],
        "verify_ms": 1e3 * t_verify,
        "recoveries": len(st["recoveries"]),
        "compiled_steps": st.get("n_compiled_steps", 0),
        "cost": st["integrated_snap"],
    }


def bench_global(problem: Problem, warm_start: bool = True) -> Row:
    """The shipped global planner (warm start from the iterative pass + exact refinement), or
    with warm_start=False one cold sparse OSQP solve + the same refinement (the paper's baseline)."""
    res = plan_global(problem, warm_start=warm_start)
    row: Row = {"method": "global" if warm_start else "global-cold", "backend": "osqp", "m": problem.m, "ok": res.ok}
    if not res.ok or res.trajectory is None:
        return {**row, "message": res.message, "time_total_ms": 1e3 * res.stats.get("time_total", 0.0)}
    rep = verify(res.trajectory, problem)
    return {**row, "verified": rep.ok, "time_total_ms": 1e3 * res.stats["time_total"],
            "cost": res.stats["integrated_snap"]}


def bench_sizes(sizes: list[int], window: int, seed: int = 0, global_max_m: int = 1000,
                norm: bool = False) -> list[Row]:
    rows: list[Row] = []
    for m in sizes:
        problem = random_problem(m, seed, norm=norm)
        it = {b: bench_iterative(problem, b, window) for b in BACKEND_ROWS}
        rows.extend(it.values())
        if m <= global_max_m:
            ref = it["compiled"]
            for g in (bench_global(problem), bench_global(problem, warm_start=False)):
                if g.get("ok") and ref.get("ok"):
                    g["time_ratio_global_over_iterative"] = g["time_total_ms"] / ref["time_total_ms"]
                    g["cost_ratio_iterative_over_global"] = ref["cost"] / g["cost"]
                rows.append(g)
    return rows


def window_sweep(windows: list[int], m: int = 30, seeds: int = 8) -> list[Row]:
    """Cost of the iterative plan relative to the global optimum, per window."""
    rows: list[Row] = []
    problems = [random_problem(m, s) for s in range(seeds)]
    globals_ = [plan_global(p) for p in problems]
    for h in windows:
        ratios: list[float] = []
        times: list[float] = []
        recov = 0
        for p, g in zip(problems, globals_, strict=True):
            r = plan_iterative(p, IterativeOptions(window=h))
            if r.ok and g.ok:
                ratios.append(r.stats["integrated_snap"] / g.stats["integrated_snap"])
                times.append(r.stats["time_total"])
                recov += len(r.stats["recoveries"])
        rows.append({
            "window": h, "m": m, "problems": seeds, "solved": len(ratios),
            "cost_ratio_median": statistics.median(ratios) if ratios else float("nan"),
            "cost_ratio_max": max(ratios) if ratios else float("nan"),
            "time_median_ms": 1e3 * statistics.median(times) if times else float("nan"),
            "recoveries": recov,
        })
    return rows


# --- local replanning (replan helper; implementation in benchmarks/bench_replan.py) ----------


def bench_replan(sizes: list[int], repeats: int = 200) -> list[Row]:
    """Latency of replanning one moved waypoint at each m (target <= 1 ms at any m)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_replan import bench_replan as run

    return run(sizes, repeats)


def _table(rows: list[Row], cols: list[str]) -> str:
    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    cells = [[fmt(r.get(c, "")) for c in cols] for r in rows]
    widths = [max(len(c), *(len(x[i]) for x in cells)) for i, c in enumerate(cols)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(cols, widths, strict=True))]
    lines += ["  ".join(x.ljust(w) for x, w in zip(cell, widths, strict=True)) for cell in cells]
    return "\n".join(lines)


def bench_quality() -> list[Row]:
    """Cost / global and success per window on random cluttered scenes (benchmarks/quality.py, ~40 s)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from quality import SUMMARY_COLS, quality_rows, table

    rows = quality_rows()
    print("\nquality on random cluttered scenes where the global QP is feasible (target: 100%, median <= 1.10)")
    print(table(rows, SUMMARY_COLS))
    return rows


def bench_minsnap(n_random: int = 5, n_fast: int = 2) -> list[Row]:
    """Side by side with minsnap-trajectories (benchmarks/minsnap_compare.py; needs the bench extra)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from minsnap_compare import COLS, INSTALL_HINT, run, table

    try:
        import minsnap_trajectories  # noqa: F401
    except ImportError:
        print(INSTALL_HINT)
        return []
    rows = run(n_random, n_fast)
    print("\nvs minsnap-trajectories, same waypoints and durations (violations > 0: outside bound/corridor)")
    print(table(rows, COLS))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 100, 1000])
    ap.add_argument("--window", type=int, default=DEFAULT_WINDOW)
    ap.add_argument("--window-sweep", action="store_true")
    ap.add_argument("--norm", action="store_true",
                    help="problems with a horizontal norm bound on velocity and acceleration (docs/bounds.md)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--quality", action="store_true", help="also run benchmarks/quality.py (~40 s)")
    ap.add_argument("--minsnap", action="store_true",
                    help="also compare with minsnap-trajectories (pip install -e '.[bench]'; ~90 s)")
    args = ap.parse_args(argv)
    # load (or, the first time on a machine, compile) the compiled pass before timing anything
    from planner_core.iterative import warm_up

    unavailable = warm_up()
    if unavailable:
        print(f"compiled pass unavailable here: {unavailable}")
    out: dict[str, list[Row]] = {}
    if args.window_sweep:
        out["window_sweep"] = window_sweep([1, 2, 3, 4, 5])
        print(_table(out["window_sweep"], list(out["window_sweep"][0])))
    else:
        rows = bench_sizes(args.sizes, args.window, norm=args.norm)
        out["sizes"] = rows
        cols = ["method", "backend", "window", "m", "ok", "time_total_ms", "step_median_us", "step_build_us",
                "step_solve_us", "step_check_us", "compiled_steps", "verify_ms", "recoveries", "cost",
                "time_ratio_global_over_iterative", "cost_ratio_iterative_over_global"]
        print(_table(rows, cols))
        out["replan"] = bench_replan(args.sizes)
        print("\nlocal replan, one moved waypoint (target <= 1 ms at any m)")
        print(_table(out["replan"], ["m", "resolved_jets", "verified", "median_ms", "p95_ms", "min_ms", "qp_ms",
                                     "cold_median_ms", "cold_p95_ms", "split_env_median_ms", "split_env_p95_ms"]))
    if args.quality:
        out["quality"] = bench_quality()
    if args.minsnap:
        out["minsnap"] = bench_minsnap()
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
