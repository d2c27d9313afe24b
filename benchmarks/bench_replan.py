"""Local replan latency: one moved waypoint in the middle of an m-waypoint mission.

The target is <= 1 ms at any m: replan must do O(change) work (one small QP,
a hull certificate of the rebuilt segments), plus O(m) numpy copies only.

    .venv/bin/python benchmarks/bench_replan.py [--json OUT.json]
    (also a section of benchmarks/planner.py)
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from planner_core.changes import MoveWaypoint, box
from planner_core.planning import plan
from planner_core.problem import Bounds, Problem
from planner_core.replan import replan
from planner_core.verify import verify


def _mission(m: int, seed: int = 0) -> Problem:
    """A random walk with 2 m of box corridor around each straight segment."""
    rng = np.random.default_rng(seed)
    steps = rng.uniform([2.0, -3.0, -0.5], [5.0, 3.0, 0.5], size=(m - 1, 3))
    wps = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
    corridors = tuple(
        box(np.minimum(a, b) - 2.0, np.maximum(a, b) + 2.0) for a, b in itertools.pairwise(wps)
    )
    return Problem.from_waypoints(wps, np.full(m - 1, 2.0), Bounds.symmetric(7.0, 6.5, 40.0, 400.0), corridors)


def bench_replan(ms: Sequence[int] = (10, 100, 1000), repeats: int = 200) -> list[dict[str, Any]]:
    """One row per m: median / p95 latency of replanning one moved waypoint."""
    rows = []
    for m in ms:
        problem = _mission(m)
        res = plan(problem)
        if not res.ok or res.trajectory is None:
            rows.append({"m": m, "error": res.message})
            continue
        traj = res.trajectory
        j = m // 2
        change = MoveWaypoint(j, problem.waypoints[j] + np.array([0.3, -0.2, 0.1]))
        first = replan(problem, traj, change)
        ok = first.ok and first.trajectory is not None and verify(first.trajectory, first.problem).ok
        for _ in range(10):  # warm caches
            replan(problem, traj, change)
        times = np.empty(repeats)
        for i in range(repeats):
            t0 = time.perf_counter()
            replan(problem, traj, change)
            times[i] = time.perf_counter() - t0
        rows.append(
            {
                "m": m,
                "resolved_jets": list(first.resolved_jets),
                "verified": bool(ok),
                "median_ms": 1e3 * float(np.median(times)),
                "p95_ms": 1e3 * float(np.percentile(times, 95)),
                "qp_ms": 1e3 * float(first.stats.get("qp_time_s", float("nan"))),
            }
        )
    return rows


def format_rows(rows: list[dict[str, Any]]) -> str:
    lines = ["| m | re-solved jets | verified | median ms | p95 ms |", "|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['m']} | plan failed: {r['error']} | | | |")
            continue
        lines.append(
            f"| {r['m']} | {r['resolved_jets']} | {r['verified']} | {r['median_ms']:.3f} | {r['p95_ms']:.3f} |"
        )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", default=None, help="write the rows here")
    ap.add_argument("--repeats", type=int, default=200)
    args = ap.parse_args(argv)
    rows = bench_replan(repeats=args.repeats)
    print("Local replan, one moved waypoint (target <= 1 ms at any m)")
    print(format_rows(rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
