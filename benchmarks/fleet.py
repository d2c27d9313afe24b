"""Fleet separation: the cost of certifying, planning and locally replanning against N other
vehicles' committed trajectories (issue 24, item 6; planner_core.separation).

Scene: our mission crosses a 100 m field along x (11 waypoints, z = 0, rest to rest, the durations
our planner needs alone). The N neighbours cross our line along y at 5 m/s at random x, on altitude
layers 0, 4 and 8 m, timed to pass our line 4-6 s before or after we pass their crossing point and
when we are >= 20 m from it (also while we wait at the start or hold at the end): every neighbour
crosses our path, but a separated plan exists.
Separation 3 m centre to centre, clock tolerance 50 ms (paid with the bound speeds).

Per N (1, 10, 50, 200):
- certify: `certify_all` of our plan against the N (broad phase, then one certificate per near
  neighbour); and one certificate for every neighbour (`certify_many`, what a publisher sends);
- plan: `plan(problem, neighbours=...)` (faces, the planner, verify, certification);
- replan: `replan` of one moved waypoint in the middle with `ReplanOptions(neighbours=...)`
  (faces of the re-solved segments, the local QP, certificate of the rebuilt span).
Targets: a local replan against 10 neighbours <= 5 ms median, against 200 <= 20 ms.

    .venv/bin/python benchmarks/fleet.py [--json OUT.json] [--repeats N]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from planner_core.bezier import segments_from_jets
from planner_core.changes import MoveWaypoint
from planner_core.planning import plan
from planner_core.problem import Bounds, FloatArray, Problem, Trajectory
from planner_core.replan import ReplanOptions, replan
from planner_core.separation import Neighbours, certify_all, certify_many

SEPARATION = 3.0
CLOCK = 0.05
SPEED = 5.0
BOUNDS = Bounds.symmetric(7.0, 6.5, 40.0, 400.0)
COUNTS = (1, 10, 50, 200)


def _ours(m: int = 11) -> tuple[Problem, Trajectory]:
    """Our problem at durations the planner needs no stretching for, and its plan alone."""
    x = np.linspace(-50.0, 50.0, m)
    wps = np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)
    problem = Problem.from_waypoints(wps, np.full(m - 1, 20.0 / (m - 1)), BOUNDS)
    alone = plan(problem).trajectory
    assert alone is not None
    return replace(problem, times=alone.times), alone


def _cruise(p0: FloatArray, p1: FloatArray, t0: float, t1: float, pieces: int = 4) -> Trajectory:
    """Constant velocity from p0 to p1 on [t0, t1] (a committed cruise leg), `pieces` segments."""
    times = np.linspace(t0, t1, pieces + 1)
    v = (p1 - p0) / (t1 - t0)
    jets = np.zeros((pieces + 1, 5, 3))
    jets[:, 0] = p0 + (times - t0)[:, None] * v
    jets[:, 1] = v
    return Trajectory(times, segments_from_jets(jets, np.diff(times)))


def _neighbours(n: int, alone: Trajectory, seed: int = 0) -> tuple[Trajectory, ...]:
    rng = np.random.default_rng(seed)
    grid = np.linspace(alone.t0, alone.t_end, 2001)
    xs = alone.evaluate(grid)[:, 0]
    out = []
    while len(out) < n:
        xk = float(rng.uniform(-55.0, 55.0))
        z = float(rng.choice([0.0, 4.0, 8.0]))
        t_ours = float(np.interp(xk, xs, grid))  # when we pass x = xk (xs increases)
        t_cross = t_ours + float(rng.choice([-1.0, 1.0])) * float(rng.uniform(4.0, 6.0))
        x_then = float(alone.evaluate(t_cross)[0])  # where we are (or wait, or hold) then
        if abs(x_then - xk) < 20.0:
            continue
        half = 40.0 / SPEED
        out.append(_cruise(np.array([xk, -40.0, z]), np.array([xk, 40.0, z]), t_cross - half, t_cross + half))
    return tuple(out)


def _ms(call: Callable[[], object], repeats: int) -> FloatArray:
    out = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        call()
        out[i] = time.perf_counter() - t0
    return 1e3 * out


def _med(ms: FloatArray) -> dict[str, float]:
    return {"median_ms": float(np.median(ms)), "p95_ms": float(np.percentile(ms, 95))}


def _row(problem: Problem, alone: Trajectory, n: int, repeats: int) -> dict[str, Any]:
    trajs = _neighbours(n, alone)
    nb = Neighbours(trajs, SEPARATION, CLOCK, speeds=(SPEED,) * n)
    row: dict[str, Any] = {"waypoints": problem.m, "neighbours": n}
    first = plan(problem, neighbours=nb)
    if not first.ok or first.trajectory is None:
        row["error"] = first.message
        return row
    traj = first.trajectory
    row["near"] = first.stats["separation"]["near"]
    row["plan_path"] = "rows" if "time-resolved" in first.message else "faces"
    ts = np.linspace(traj.t0, traj.t_end + 1.0, 4001)
    row["min_distance_sampled"] = float(min(np.linalg.norm(traj.evaluate(ts) - t.evaluate(ts), axis=1).min()
                                            for t in trajs))
    resolved = nb.for_bounds(problem.bounds)
    row["certify_near"] = _med(_ms(lambda: certify_all(traj, resolved), repeats))
    every = certify_many(traj, trajs, SEPARATION, clock_tolerance=CLOCK, speeds=[(resolved.our_speed, SPEED)] * n)
    row["certified_all"] = all(c.ok for c in every)
    row["certify_each"] = _med(_ms(lambda: certify_many(traj, trajs, SEPARATION, clock_tolerance=CLOCK,
                                                        speeds=[(resolved.our_speed, SPEED)] * n), max(3, repeats // 4)))
    row["plan"] = _med(_ms(lambda: plan(problem, neighbours=nb), max(3, repeats // 4)))
    j = problem.m // 2
    change = MoveWaypoint(j, problem.waypoints[j] + np.array([0.5, 0.8, 0.3]))
    opts = ReplanOptions(neighbours=replace(nb, reference=traj))
    r = replan(problem, traj, change, options=opts)
    row["replan_ok"] = bool(r.ok)
    if r.ok and r.trajectory is not None:
        row["replan_near"] = r.stats["separation"]["near"]
        row["replan_path"] = "rows" if r.stats.get("separation_rows") else "faces"
        row["replan"] = _med(_ms(lambda: replan(problem, traj, change, options=opts), repeats))
        row["replan_bare"] = _med(_ms(lambda: replan(problem, traj, change), repeats))
    else:
        row["replan_error"] = r.message
    return row


def bench(counts: Sequence[int] = COUNTS, repeats: int = 20) -> list[dict[str, Any]]:
    """Two scenes: 11 waypoints (10 m segments: one face per segment and neighbour is enough), and
    3 waypoints (50 m segments that neighbours cross within their span: time-resolved rows)."""
    rows = []
    for m in (11, 3):
        problem, alone = _ours(m)
        rows += [_row(problem, alone, n, repeats) for n in counts]
    return rows


def format_rows(rows: list[dict[str, Any]]) -> str:
    lines = ["| waypoints | neighbours | near | min dist (m) | certify near med/p95 ms | certify all N med ms | "
             "plan med ms (path) | replan med/p95 ms (path) | replan w/o neighbours med ms |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['waypoints']} | {r['neighbours']} | plan failed: {r['error']} | | | | | | |")
            continue
        rep = (f"{r['replan']['median_ms']:.2f} / {r['replan']['p95_ms']:.2f} ({r['replan_path']})" if "replan" in r
               else f"failed: {r.get('replan_error')}")
        bare = f"{r['replan_bare']['median_ms']:.2f}" if "replan_bare" in r else ""
        lines.append(f"| {r['waypoints']} | {r['neighbours']} | {r['near']} | {r['min_distance_sampled']:.2f} | "
                     f"{r['certify_near']['median_ms']:.2f} / {r['certify_near']['p95_ms']:.2f} | "
                     f"{r['certify_each']['median_ms']:.2f} | {r['plan']['median_ms']:.2f} ({r['plan_path']}) | "
                     f"{rep} | {bare} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", default=None, help="write the rows here")
    ap.add_argument("--repeats", type=int, default=20)
    args = ap.parse_args(argv)
    rows = bench(repeats=args.repeats)
    print(f"Fleet separation: s = {SEPARATION} m, clock tolerance {CLOCK * 1e3:.0f} ms "
          "(targets: replan vs 10 <= 5 ms median, vs 200 <= 20 ms)")
    print(format_rows(rows))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
