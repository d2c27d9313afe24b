"""Local replan latency: one moved waypoint in the middle of an m-waypoint mission.

The target is <= 1 ms at any m: replan must do O(change) work (one small QP,
a hull certificate of the rebuilt segments), plus O(m) numpy copies only.

Three cases per m:
- hot: the same move repeated (the benchmark's headline; per-duration caches warm);
- cold: durations differ per segment and each repeat moves a different waypoint,
  so the per-duration maps of the touched segments are built on the spot;
- split+env: as the companion calls it (companion.route.local_replan): split a
  little ahead of "now" (a new segment duration every time) and rebuild corridors
  from an environment.

    .venv/bin/python benchmarks/bench_replan.py [--json OUT.json] [--repeats N]
    (also a section of benchmarks/planner.py)
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from planner_core.changes import ChangeSet, MoveWaypoint, box
from planner_core.planning import plan
from planner_core.problem import Bounds, FloatArray, Problem, Trajectory
from planner_core.replan import Environment, ReplanOptions, replan
from planner_core.verify import verify

OFFSET = np.array([0.3, -0.2, 0.1])


def _mission(m: int, seed: int = 0, varied: bool = False) -> Problem:
    """A random walk with 2 m of box corridor around each straight segment."""
    rng = np.random.default_rng(seed)
    steps = rng.uniform([2.0, -3.0, -0.5], [5.0, 3.0, 0.5], size=(m - 1, 3))
    wps = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
    corridors = tuple(
        box(np.minimum(a, b) - 2.0, np.maximum(a, b) + 2.0) for a, b in itertools.pairwise(wps)
    )
    durations = rng.uniform(1.8, 2.6, m - 1) if varied else np.full(m - 1, 2.0)
    return Problem.from_waypoints(wps, durations, Bounds.symmetric(7.0, 6.5, 40.0, 400.0), corridors)


def _times_ms(calls: Sequence[Callable[[], object]]) -> FloatArray:
    out = np.empty(len(calls))
    for i, call in enumerate(calls):
        t0 = time.perf_counter()
        call()
        out[i] = time.perf_counter() - t0
    return 1e3 * out


def _stats(prefix: str, ms: FloatArray) -> dict[str, float]:
    return {f"{prefix}median_ms": float(np.median(ms)), f"{prefix}p95_ms": float(np.percentile(ms, 95))}


def _hot(m: int, repeats: int) -> dict[str, Any]:
    problem = _mission(m)
    res = plan(problem)
    if not res.ok or res.trajectory is None:
        return {"m": m, "error": res.message}
    traj = res.trajectory
    j = m // 2
    change = MoveWaypoint(j, problem.waypoints[j] + OFFSET)
    first = replan(problem, traj, change)
    ok = first.ok and first.trajectory is not None and verify(first.trajectory, first.problem).ok
    warm = first
    for _ in range(10):  # warm caches
        warm = replan(problem, traj, change)
    ms = _times_ms([lambda: replan(problem, traj, change)] * repeats)
    return {
        "m": m,
        "resolved_jets": list(first.resolved_jets),
        "verified": bool(ok),
        **_stats("", ms),
        "min_ms": float(ms.min()),
        "qp_ms": 1e3 * float(warm.stats.get("qp_time_s", float("nan"))),  # the local QP of a warm call
    }


def _cold_calls(problem: Problem, traj: Trajectory, repeats: int) -> tuple[list[Callable[[], object]], list[Callable[[], object]]]:
    m = problem.m
    rng = np.random.default_rng(1)
    js = [int(j) for j in rng.permutation(np.arange(2, m - 2))] if m > 4 else [1]
    js = (js * (repeats // len(js) + 1))[:repeats]
    wps, times = problem.waypoints, problem.times
    env = Environment((), (wps.min(axis=0) - 10.0, wps.max(axis=0) + 10.0), 0.3)
    opts = ReplanOptions(environment=env)
    cold = [lambda j=j: replan(problem, traj, MoveWaypoint(j, wps[j] + OFFSET)) for j in js]
    # the companion moves the waypoint being flown to, from a split 0.37 s into its segment
    split = [
        lambda j=j: replan(
            problem, traj, ChangeSet((MoveWaypoint(j, wps[j] + OFFSET),), from_time=float(times[j - 1]) + 0.37), options=opts
        )
        for j in js
    ]
    return cold, split


def _cold(m: int, repeats: int) -> dict[str, Any]:
    problem = _mission(m, varied=True)
    res = plan(problem)
    if not res.ok or res.trajectory is None:
        return {"cold_error": res.message}
    cold, split = _cold_calls(problem, res.trajectory, repeats)
    for call in (cold[0], split[0]):
        r = call()
        if not getattr(r, "ok", False):
            return {"cold_error": getattr(r, "message", "?")}
    return {**_stats("cold_", _times_ms(cold)), **_stats("split_env_", _times_ms(split))}


def bench_replan(ms: Sequence[int] = (10, 100, 1000), repeats: int = 200) -> list[dict[str, Any]]:
    """One row per m: latency of replanning one moved waypoint (hot, cold, companion-style)."""
    rows = []
    for m in ms:
        row = _hot(m, repeats)
        if "error" not in row:
            row.update(_cold(m, repeats))
        rows.append(row)
    return rows


def format_rows(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| m | re-solved jets | verified | median ms | p95 ms | min ms | cold median / p95 ms | split+env median / p95 ms |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['m']} | plan failed: {r['error']} | | | | | | |")
            continue
        if "cold_error" in r:
            cold = split = f"failed: {r['cold_error']}"
        else:
            cold = f"{r['cold_median_ms']:.3f} / {r['cold_p95_ms']:.3f}"
            split = f"{r['split_env_median_ms']:.3f} / {r['split_env_p95_ms']:.3f}"
        lines.append(
            f"| {r['m']} | {r['resolved_jets']} | {r['verified']} | {r['median_ms']:.3f} | {r['p95_ms']:.3f} "
            f"| {r['min_ms']:.3f} | {cold} | {split} |"
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
