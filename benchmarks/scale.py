"""Planning at scale: generated scenes, end to end (scenario JSON -> corridors -> plan -> verify).

    .venv/bin/python benchmarks/scale.py [--rows 15/10 60/50 200/200 500/1000] [--repeats 3] [--json PATH]

Scenes (fixed seeds): random axis-aligned box obstacles (0.5-3 m wide, 1-6 m tall) in a
flat map whose area grows with the obstacle count (~110 m^2 an obstacle), then a waypoint
chain (legs 2.5-7 m) whose every leg keeps more than 2 x radius + 0.1 m from every box,
so no leg is blocked. Bounds v 5, a 4, j 12, s 40 per axis; durations leg / 2.5 m/s
(rest to rest), so short legs with sharp turns are tight and recovery stretches them.

Stages, each the median over `--repeats` runs: parse (json.loads + load_scenario without
the corridor build), corridors (build_corridors as load_scenario calls it), plan (the
iterative planner, recoveries included), verify (`verify` of the returned plan), search
(the uniform duration-scale search, which runs only when the planner's own recovery
fails), and end_to_end (all of them in one go, as `python -m planner_core plan` does
them). recoveries / stretches count the planner's recoveries and the duration stretches
among them; recovery_max / recovery_total are their cost (`stats.recoveries[i].time`).

Wall-clock medians on whatever machine runs this; compare ratios, not absolute numbers,
when the machine is shared.
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

import planner_core.geometry as cor
from planner_core import plan
from planner_core.formats.io import load_scenario

Row = dict[str, Any]
RADIUS = 0.3
BOUNDS = {"velocity": 5.0, "acceleration": 4.0, "jerk": 12.0, "snap": 40.0}
SPEED = 2.5  # m/s: durations = leg length / SPEED
AREA_PER_OBSTACLE = 110.0  # m^2
HEIGHT = 8.0
ROWS = ((15, 10), (60, 50), (200, 200), (500, 1000))


def _box_distance(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(p, n) distance from points to axis-aligned boxes [lo_n, hi_n]."""
    d = np.maximum(np.maximum(lo[None] - points[:, None], points[:, None] - hi[None]), 0.0)
    return np.asarray(np.linalg.norm(d, axis=-1))


def scene(n_obstacles: int, m: int, seed: int = 0, vertices: bool = False) -> dict[str, Any]:
    """A scenario dict (the JSON format of examples/) with `n_obstacles` boxes and `m` waypoints;
    `vertices`: each box as its 8 corners ({"vertices": ...}, as a mapping tool would send it)
    instead of {A, b}."""
    rng = np.random.default_rng(seed)
    side = float(np.sqrt(AREA_PER_OBSTACLE * max(n_obstacles, 1)))
    side = max(side, 30.0)
    size = np.array([side, side, HEIGHT])
    centres = rng.uniform([0.0, 0.0, 0.0], size, (n_obstacles, 3))
    extent = np.concatenate([rng.uniform(0.5, 3.0, (n_obstacles, 2)), rng.uniform(1.0, 6.0, (n_obstacles, 1))], 1)
    lo, hi = centres - extent / 2, centres + extent / 2
    clear = 2 * RADIUS + 0.1  # sampled every 0.05 m: the true distance is > 2 r + 0.075
    margin = np.array([1.0, 1.0, 0.8])
    inner_lo, inner_hi = margin, size - margin
    # the first waypoint: anywhere clear
    while True:
        p = rng.uniform(inner_lo, inner_hi)
        if n_obstacles == 0 or float(_box_distance(p[None], lo, hi).min()) > clear:
            break
    wps = [p]
    tries = 0
    while len(wps) < m:
        tries += 1
        if tries > 200 * m:
            raise RuntimeError(f"scene({n_obstacles}, {m}, {seed}): could not place waypoints")
        step = rng.normal(size=3) * np.array([1.0, 1.0, 0.25])
        step *= rng.uniform(2.5, 7.0) / np.linalg.norm(step)
        nxt = wps[-1] + step
        if np.any(nxt < inner_lo) or np.any(nxt > inner_hi):
            continue
        if n_obstacles:
            # only boxes near the leg can be within `clear` of it
            near = np.all((lo <= np.maximum(wps[-1], nxt) + clear + 1) & (hi >= np.minimum(wps[-1], nxt) - clear - 1), 1)
            if np.any(near):
                n_s = max(2, int(np.ceil(np.linalg.norm(step) / 0.05)) + 1)
                pts = wps[-1] + np.linspace(0.0, 1.0, n_s)[:, None] * step
                if float(_box_distance(pts, lo[near], hi[near]).min()) <= clear:
                    continue
        wps.append(nxt)
    W = np.array(wps)
    durations = np.linalg.norm(np.diff(W, axis=0), axis=1) / SPEED
    eye = np.eye(3)
    A = np.concatenate([eye, -eye]).tolist()
    return {
        "description": f"benchmarks/scale.py scene: {n_obstacles} boxes, {m} waypoints, seed {seed}",
        "frame": "enu",
        "waypoints": W.tolist(),
        "durations": durations.tolist(),
        "bounds": BOUNDS,
        "map": {"min": [0.0, 0.0, 0.0], "max": size.tolist()},
        "vehicle_radius": RADIUS,
        "obstacles": [box_vertices(w, h) if vertices else {"A": A, "b": np.concatenate([h, -w]).tolist()}
                      for w, h in zip(lo, hi, strict=True)],
    }


def box_vertices(lo: np.ndarray, hi: np.ndarray) -> dict[str, Any]:
    """The box [lo, hi] as {"vertices": its 8 corners}."""
    bits = (np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1
    return {"vertices": np.where(bits.astype(bool), hi[None, :], lo[None, :]).tolist()}


class _CorridorTimer:
    """Times `build_corridors` as load_scenario calls it (load_scenario imports it lazily)."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self._inner = cor.build_corridors

    def __enter__(self) -> _CorridorTimer:
        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return self._inner(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - t0

        cor.build_corridors = timed  # type: ignore[assignment]
        return self

    def __exit__(self, *exc: object) -> None:
        cor.build_corridors = self._inner  # type: ignore[assignment]


def run_once(text: str) -> Row:
    cor.clear_vertex_cache()  # a user's obstacles are new to the process
    t0 = time.perf_counter()
    with _CorridorTimer() as timer:
        sc = load_scenario(json.loads(text))
    t_load = time.perf_counter() - t0
    res = plan(sc.problem)
    t_end = time.perf_counter() - t0
    st = res.stats
    recs = [r for r in st.get("recoveries", []) if r.get("action") in ("stretch", "uniform stretch")]
    costs = [float(r.get("time", float("nan"))) for r in st.get("recoveries", [])]
    return {
        "ok": res.ok,
        "verified": bool(st.get("verified", False)),
        "message": res.message if not res.ok else "",
        "end_to_end": t_end,
        "parse": t_load - timer.seconds,
        "corridors": timer.seconds,
        "plan": float(st.get("time_total", float("nan"))),
        "verify": float(st.get("time_verify", float("nan"))),
        "search": float(st.get("scale_search", {}).get("time_scale_search", 0.0)),
        "recoveries": len(st.get("recoveries", [])),
        "stretches": len(recs),
        "recovery_max": max(costs) if costs else 0.0,
        "recovery_total": sum(c for c in costs if np.isfinite(c)),
    }


def bench_row(n_obstacles: int, m: int, seed: int, repeats: int) -> Row:
    text = json.dumps(scene(n_obstacles, m, seed))
    runs = [run_once(text) for _ in range(repeats + 1)][1:]  # the first one warms caches and the kernel
    row: Row = {"obstacles": n_obstacles, "waypoints": m, "seed": seed, "ok": all(r["ok"] for r in runs),
                "verified": all(r["verified"] for r in runs), "message": runs[0]["message"],
                "recoveries": runs[0]["recoveries"], "stretches": runs[0]["stretches"]}
    for key in ("end_to_end", "parse", "corridors", "plan", "verify", "search", "recovery_max", "recovery_total"):
        row[f"{key}_ms"] = 1e3 * statistics.median(r[key] for r in runs)
    return row


COLS = ["obstacles", "waypoints", "ok", "verified", "end_to_end_ms", "parse_ms", "corridors_ms", "plan_ms",
        "verify_ms", "search_ms", "recoveries", "stretches", "recovery_max_ms", "recovery_total_ms"]


def table(rows: list[Row]) -> str:
    def fmt(v: Any) -> str:
        return f"{v:.1f}" if isinstance(v, float) else str(v)

    cells = [COLS] + [[fmt(r[c]) for c in COLS] for r in rows]
    widths = [max(len(c[i]) for c in cells) for i in range(len(COLS))]
    return "\n".join("  ".join(c[i].rjust(widths[i]) for i in range(len(COLS))) for c in cells)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", nargs="+", default=[f"{n}/{m}" for n, m in ROWS], help="obstacles/waypoints")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    rows = []
    for spec in args.rows:
        n, m = (int(x) for x in spec.split("/"))
        rows.append(bench_row(n, m, args.seed, args.repeats))
        print(table(rows[-1:]).splitlines()[-1] if len(rows) > 1 else table(rows), flush=True)
    for r in rows:
        if r["message"]:
            print(f"{r['obstacles']}/{r['waypoints']}: {r['message']}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
