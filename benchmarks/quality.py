"""Plan quality on random cluttered scenarios: iterative (per window, +-recovery) vs the global QP.

    python benchmarks/quality.py [--scenarios 50] [--fast 15] [--seed 0] [--json PATH]

Scenarios (seeded): 6-13 waypoints in a box map, box and triangular-prism
obstacles placed near the path but never blocking a straight segment
(reject-sampled with the corridor builder, vehicle radius 0.3), corridors from
`planner_core.geometry.build_corridors`, times from
`planner_core.timing.allocate_times`; bounds v 3-7, a 3-6.5 and jerk / snap
drawn low enough to bind. "Fast" variants fly some of the scenes with every
duration scaled by 0.6-0.85, which makes the bounds bind more often.

Cost is the integrated squared snap of the whole trajectory, computed exactly
from the control points for both planners (`snap_cost`). Scenarios where the
global QP is infeasible are skipped (and counted): the global optimum is the
reference. Every returned trajectory is also checked with `verify`.

Every function returns plain dict rows (benchmarks/planner.py reuses them).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from planner_core import Bounds, IterativeOptions, Polytope, Problem, Trajectory, verify
from planner_core.constraints import integrated_cost
from planner_core.geometry import (
    CorridorError,
    build_corridors,
    polytope_from_box,
    polytope_from_vertices,
)
from planner_core.global_qp import plan_global
from planner_core.iterative import plan_iterative
from planner_core.timing import allocate_times

Row = dict[str, Any]

RADIUS = 0.3
WINDOWS = (1, 2, 3, 4, 5, 6)  # 5, 6: beyond the brief, to show where the cost ratio flattens
MAP_SIZE = np.array([30.0, 30.0, 6.0])
BIND_TOL = 1e-3  # a bound "binds" at the optimum when some hull point is within 0.1% of it


@dataclass(frozen=True)
class Scenario:
    name: str
    problem: Problem
    obstacles: tuple[Polytope, ...]
    map_box: tuple[np.ndarray, np.ndarray]
    fast: bool = False


def snap_cost(traj: Trajectory) -> float:
    """∫ |snap(t)|^2 dt, exact: Bernstein Gram quadratic form of the degree-5 snap hodograph."""
    return integrated_cost(traj.control_points, np.diff(traj.times), 4)


# --- scenario generation -------------------------------------------------------------------


def _waypoints(rng: np.random.Generator, m: int) -> np.ndarray:
    lo, hi = np.array([1.0, 1.0, 0.8]), MAP_SIZE - np.array([1.0, 1.0, 0.8])
    wps = [rng.uniform(lo, hi)]
    while len(wps) < m:
        step = rng.normal(size=3) * np.array([1.0, 1.0, 0.25])
        step *= rng.uniform(2.5, 7.0) / np.linalg.norm(step)
        nxt = wps[-1] + step
        if np.all(nxt >= lo) and np.all(nxt <= hi):
            wps.append(nxt)
    return np.array(wps)


def _obstacle(rng: np.random.Generator, wps: np.ndarray) -> Polytope:
    j = int(rng.integers(0, wps.shape[0] - 1))
    centre = wps[j] + rng.random() * (wps[j + 1] - wps[j]) + rng.normal(size=3) * np.array([1.5, 1.5, 0.6])
    if rng.random() < 0.5:
        return polytope_from_box(centre, rng.uniform(0.3, 2.5, 3))
    # vertical triangular prism
    ang = rng.uniform(0, 2 * np.pi) + np.array([0.0, 2.1, 4.2]) + rng.normal(size=3) * 0.3
    tri = centre[:2] + rng.uniform(0.4, 1.5, (3, 1)) * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    h = rng.uniform(0.5, 3.0)
    verts = [[*p, centre[2] + s * h / 2] for p in tri for s in (-1.0, 1.0)]
    return polytope_from_vertices(np.array(verts))


def _bounds(rng: np.random.Generator) -> Bounds:
    return Bounds.symmetric(
        float(rng.uniform(3.0, 7.0)), float(rng.uniform(3.0, 6.5)),
        float(rng.uniform(4.0, 15.0)), float(rng.uniform(8.0, 40.0)),
    )


def random_scenario(seed: int) -> Scenario:
    """One feasible cluttered scene: no obstacle blocks a straight segment (reject-sampled)."""
    rng = np.random.default_rng(seed)
    box = (np.zeros(3), MAP_SIZE.copy())
    while True:
        wps = _waypoints(rng, int(rng.integers(6, 14)))
        obstacles: list[Polytope] = []
        for _ in range(int(rng.integers(8, 25))):
            cand = _obstacle(rng, wps)
            try:  # blocking is a per-obstacle property, so testing the candidate alone is enough
                build_corridors(wps, [cand], box, RADIUS)
            except CorridorError:
                continue
            obstacles.append(cand)
        try:
            corridors = build_corridors(wps, obstacles, box, RADIUS)
        except CorridorError:
            continue
        bounds = _bounds(rng)
        times = allocate_times(wps, bounds, corridors=corridors)
        problem = Problem.from_waypoints(wps, np.diff(times), bounds, corridors)
        return Scenario(f"s{seed}", problem, tuple(obstacles), box)


def faster(sc: Scenario, factor: float) -> Scenario:
    """The same scene flown with every duration scaled by `factor` < 1."""
    p = sc.problem
    times = p.times[0] + factor * (p.times - p.times[0])
    return replace(sc, name=f"{sc.name}x{factor:.2f}", problem=replace(p, times=times), fast=True)


def scenarios(n: int, n_fast: int, seed: int = 0) -> list[Scenario]:
    base = [random_scenario(seed * 100_000 + i) for i in range(n)]
    rng = np.random.default_rng(seed + 7)
    picks = rng.choice(n, size=min(n_fast, n), replace=False)
    return base + [faster(base[int(i)], float(rng.uniform(0.6, 0.85))) for i in picks]


# --- planning and comparison ---------------------------------------------------------------


def _verified(traj: Trajectory, problem: Problem) -> bool:
    checked = problem if np.array_equal(traj.times, problem.times) else replace(problem, times=traj.times)
    return verify(traj, checked).ok


def binding_orders(traj: Trajectory, bounds: Bounds) -> list[int]:
    """Derivative orders (1..4) whose bound some certified hodograph point (the control points of
    the planner's de Casteljau pieces) reaches (within BIND_TOL)."""
    from planner_core.constraints import certified_points

    d = np.diff(traj.times)
    out = []
    for k in range(1, 5):
        pts = certified_points(traj.control_points, k, d)
        use = np.maximum(pts / bounds.hi[k - 1], pts / bounds.lo[k - 1])
        if float(use.max()) >= 1.0 - BIND_TOL:
            out.append(k)
    return out


def run_global(sc: Scenario) -> Row:
    res = plan_global(sc.problem)
    row: Row = {"scenario": sc.name, "m": sc.problem.m, "fast": sc.fast, "ok": res.ok,
                "time_s": res.stats.get("time_total", float("nan"))}
    if not res.ok or res.trajectory is None:
        return {**row, "message": res.message}
    traj = res.trajectory
    return {**row, "verified": _verified(traj, sc.problem), "cost": snap_cost(traj),
            "binding": binding_orders(traj, sc.problem.bounds)}


def run_iterative(sc: Scenario, opts: IterativeOptions) -> Row:
    res = plan_iterative(sc.problem, opts)
    row: Row = {"scenario": sc.name, "ok": res.ok, "time_s": res.stats.get("time_total", float("nan")),
                "recoveries": len(res.stats.get("recoveries", []))}
    if not res.ok or res.trajectory is None:
        return {**row, "message": res.message}
    traj = res.trajectory
    return {**row, "verified": _verified(traj, sc.problem), "cost": snap_cost(traj),
            "stretched": not np.array_equal(traj.times, sc.problem.times)}


def configs() -> list[tuple[str, IterativeOptions]]:
    out = [("default", IterativeOptions())]
    for h in WINDOWS:
        for rec in (True, False):
            out.append((f"H={h}{'' if rec else ' norec'}", IterativeOptions(window=h, recover=rec)))
    return out


def _pct(x: list[float], q: float) -> float:
    return float(np.percentile(x, q)) if x else float("nan")


def summarise(name: str, opts: IterativeOptions, rows: list[Row], globals_: list[Row]) -> Row:
    """One table row: success / cost ratio / per-waypoint time over scenarios the global solved."""
    ratios, per_wp = [], []
    ok = verified_fail = stretched = 0
    for r, g in zip(rows, globals_, strict=True):
        if not r["ok"]:
            continue
        if not r["verified"]:
            verified_fail += 1
            continue
        ok += 1
        per_wp.append(r["time_s"] / max(g["m"] - 2, 1))
        if r["stretched"]:
            stretched += 1  # a different (longer) problem: its cost is not comparable
        else:
            ratios.append(r["cost"] / g["cost"])
    n = len(rows)
    return {
        "config": name, "window": opts.window, "recover": opts.recover, "cost": opts.cost,
        "scenarios": n, "succeeded": ok, "success_rate": ok / n if n else float("nan"),
        "verify_failures": verified_fail, "stretched": stretched,
        "cost_ratio_median": _pct(ratios, 50), "cost_ratio_p95": _pct(ratios, 95),
        "cost_ratio_max": max(ratios) if ratios else float("nan"),
        "cost_ratio_min": min(ratios) if ratios else float("nan"),
        "per_waypoint_ms_median": 1e3 * _pct(per_wp, 50),
        "recoveries": sum(r["recoveries"] for r in rows),
    }


def quality(n: int = 50, n_fast: int = 15, seed: int = 0) -> dict[str, Any]:
    """Global once per scenario, every config on the scenarios the global solved; summary rows."""
    scs = scenarios(n, n_fast, seed)
    g_all = [run_global(sc) for sc in scs]
    keep = [i for i, g in enumerate(g_all) if g["ok"] and g["verified"]]
    kept, g_kept = [scs[i] for i in keep], [g_all[i] for i in keep]
    summary: list[Row] = []
    details: dict[str, list[Row]] = {}
    done: dict[IterativeOptions, list[Row]] = {}
    for name, opts in configs():
        rows = done.get(opts) or [run_iterative(sc, opts) for sc in kept]
        done[opts] = rows
        details[name] = rows
        summary.append(summarise(name, opts, rows, g_kept))
    binds = [g.get("binding", []) for g in g_kept]
    info: Row = {
        "scenarios": len(scs), "fast_variants": sum(sc.fast for sc in scs),
        "global_infeasible": len(scs) - len(keep),
        "global_infeasible_fast": sum(1 for sc, g in zip(scs, g_all, strict=True) if sc.fast and not g["ok"]),
        "global_verify_failures": sum(1 for g in g_all if g["ok"] and not g["verified"]),
        "waypoints_min": min(sc.problem.m for sc in scs), "waypoints_max": max(sc.problem.m for sc in scs),
        "obstacles_median": float(np.median([len(sc.obstacles) for sc in scs])),
        "global_per_waypoint_ms_median": 1e3 * _pct([g["time_s"] / (g["m"] - 2) for g in g_kept], 50),
        **{f"binding_order{k}": sum(k in b for b in binds) for k in range(1, 5)},
        "binding_any": sum(bool(b) for b in binds),
    }
    return {"info": info, "summary": summary, "global": g_all, "iterative": details}


def quality_rows(n: int = 50, n_fast: int = 15, seed: int = 0) -> list[Row]:
    """Summary rows only (for benchmarks/planner.py)."""
    rows: list[Row] = quality(n, n_fast, seed)["summary"]
    return rows


SUMMARY_COLS = ["config", "scenarios", "succeeded", "verify_failures", "stretched", "cost_ratio_median",
                "cost_ratio_p95", "cost_ratio_max", "per_waypoint_ms_median", "recoveries"]


def table(rows: list[Row], cols: list[str]) -> str:
    def fmt(v: Any) -> str:
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    cells = [[fmt(r.get(c, "")) for c in cols] for r in rows]
    widths = [max(len(c), *(len(x[i]) for x in cells)) for i, c in enumerate(cols)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(cols, widths, strict=True))]
    lines += ["  ".join(x.ljust(w) for x, w in zip(cell, widths, strict=True)) for cell in cells]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", type=int, default=50)
    ap.add_argument("--fast", type=int, default=15, help="how many scenes also get a faster variant")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    out = quality(args.scenarios, args.fast, args.seed)
    info = out["info"]
    print(f"{info['scenarios']} scenarios ({info['fast_variants']} flown faster), "
          f"{info['waypoints_min']}-{info['waypoints_max']} waypoints, median {info['obstacles_median']:g} "
          f"obstacles; global infeasible on {info['global_infeasible']} (fast: {info['global_infeasible_fast']}), "
          "skipped")
    print(f"bounds binding at the global optimum: v {info['binding_order1']}, a {info['binding_order2']}, "
          f"j {info['binding_order3']}, s {info['binding_order4']}, any {info['binding_any']} "
          f"of {info['scenarios'] - info['global_infeasible']}; "
          f"global per-waypoint {info['global_per_waypoint_ms_median']:.3g} ms")
    print(table(out["summary"], SUMMARY_COLS))
    print(f"({time.perf_counter() - t0:.1f} s)")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
