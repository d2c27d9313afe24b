"""Corridor benchmark: the pop-up obstacle path (`update_corridors`) and a full build.

    .venv/bin/python benchmarks/corridors.py [--repeats N] [--json PATH]

Cases:
- scenario2_popup: examples/scenario2.json's corridors, then the pop-up box of
  examples/scenario2_popup.json moved east until the leg it sits on clears it (as
  the demo does: the original box swallows waypoint 2, which is rejected before
  any corridor work). `update_corridors(..., prune=False)`, the in-flight path;
  "cold" clears the vertex cache first (a new obstacle), "warm" does not.
- flight_popup: benchmarks/service.py's flight (two laps of a rectangle, no known
  obstacles, so map-box corridors) and a small box inside a corner the curve cuts:
  no face certifies it, so every corridor gets a plane (the service's case).
- long_popup: the same with 1000 waypoints and a small box beside segment 500: only
  the corridors whose analysis box holds the box are touched.
- scenario2_build: `build_corridors` for all of scenario 2 (what a replan does,
  per segment, for the pieces of a split segment).
- scale_build: `build_corridors` for benchmarks/scale.py's 500 boxes / 1000 waypoints
  scene, from cold (vertex cache cleared: a user's obstacles are new).

Wall-clock medians on whatever machine runs this; compare ratios, not absolute
numbers, when the machine is shared.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from planner_core import geometry as cor
from planner_core.formats.io import load_scenario
from planner_core.problem import Polytope

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
Row = dict[str, Any]


def _time(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times), 1e3 * min(times)


def scenario2_popup() -> tuple[np.ndarray, tuple[Polytope, ...], list[Polytope], Polytope, Any, float]:
    sc = load_scenario(json.loads((EXAMPLES / "scenario2.json").read_text()))
    raw = json.loads((EXAMPLES / "scenario2_popup.json").read_text())["obstacles"][0]
    A, b = np.asarray(raw["A"], dtype=float), np.asarray(raw["b"], dtype=float)
    x_line = float(sc.problem.waypoints[1, 0])
    x_min = -b[int(np.argmin(A[:, 0]))]
    shift = max(0.0, x_line + 2 * sc.vehicle_radius + 0.2 - x_min)
    popup = Polytope(A, b + A @ np.array([shift, 0.0, 0.0]))
    wps = sc.problem.waypoints
    corridors = cor.build_corridors(wps, sc.obstacles, sc.map_box, sc.vehicle_radius)
    return wps, corridors, list(sc.obstacles), popup, sc.map_box, sc.vehicle_radius


def flight_popup() -> tuple[np.ndarray, tuple[Polytope, ...], Polytope, Any, float]:
    lap = [[8, 0, 3], [8, 6, 3.5], [0, 6, 3.5], [0, 0, 3]]
    wps = np.array([[0, 0, 3], *lap, *lap], dtype=float)
    map_box = (np.array([-5.0, -5.0, 0.0]), np.array([13.0, 11.0, 8.0]))
    r = 0.3
    corridors = cor.build_corridors(wps, [], map_box, r)
    return wps, corridors, cor.polytope_from_box([7.0, 1.0, 3.1], [0.2, 0.2, 0.2]), map_box, r


def long_popup(m: int = 1000, seed: int = 0) -> tuple[np.ndarray, tuple[Polytope, ...], Polytope, Any, float]:
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=(m - 1, 3)) * [2.0, 2.0, 0.3]
    wps = np.cumsum(np.vstack([np.zeros(3), steps]), axis=0)
    map_box = (wps.min(axis=0) - 5.0, wps.max(axis=0) + 5.0)
    r = 0.3
    corridors = tuple(cor.build_corridors(wps[j : j + 2], [], map_box, r)[0] for j in range(m - 1))
    j = m // 2
    mid = 0.5 * (wps[j] + wps[j + 1])
    d = wps[j + 1] - wps[j]
    side = np.cross(d, [0.0, 0.0, 1.0])
    side /= max(float(np.linalg.norm(side)), 1e-9)
    centre = mid + 1.0 * side
    popup = cor.polytope_from_box(centre, [0.2, 0.2, 0.2])
    return wps, corridors, popup, map_box, r


def bench(repeats: int = 50) -> list[Row]:
    rows: list[Row] = []
    wps, cors, obstacles, popup, map_box, r = scenario2_popup()

    def update(cold: bool) -> Callable[[], object]:
        def run() -> object:
            if cold:
                cor.clear_vertex_cache()
            return cor.update_corridors(wps, cors, obstacles, [popup], map_box, r, prune=False)
        return run

    _, changed = cor.update_corridors(wps, cors, obstacles, [popup], map_box, r, prune=False)
    for cold in (True, False):
        med, best = _time(update(cold), repeats)
        rows.append({"case": "scenario2_popup", "cold": cold, "changed": changed, "median_ms": med, "min_ms": best})
    med, best = _time(lambda: cor.build_corridors(wps, obstacles, map_box, r), max(repeats // 5, 3))
    rows.append({"case": "scenario2_build", "segments": len(cors), "median_ms": med, "min_ms": best})

    fw, fcors, fpop, fmap, fr = flight_popup()

    def flight() -> object:
        cor.clear_vertex_cache()
        return cor.update_corridors(fw, fcors, [], [fpop], fmap, fr, prune=False)

    _, changed = cor.update_corridors(fw, fcors, [], [fpop], fmap, fr, prune=False)
    med, best = _time(flight, repeats)
    rows.append({"case": "flight_popup", "cold": True, "changed": changed, "median_ms": med, "min_ms": best})

    lw, lcors, lpop, lmap, lr = long_popup()
    _, changed = cor.update_corridors(lw, lcors, [], [lpop], lmap, lr, prune=False)
    med, best = _time(lambda: cor.update_corridors(lw, lcors, [], [lpop], lmap, lr, prune=False), repeats)
    rows.append({"case": "long_popup", "segments": len(lcors), "changed": changed, "median_ms": med, "min_ms": best})

    from benchmarks.scale import scene

    raw = scene(500, 1000)
    sc_wps = np.asarray(raw["waypoints"], dtype=float)
    boxes = [Polytope(np.asarray(o["A"], dtype=float), np.asarray(o["b"], dtype=float)) for o in raw["obstacles"]]
    sc_map = (np.asarray(raw["map"]["min"], dtype=float), np.asarray(raw["map"]["max"], dtype=float))

    def scale_build() -> object:
        cor.clear_vertex_cache()
        return cor.build_corridors(sc_wps, boxes, sc_map, float(raw["vehicle_radius"]))

    med, best = _time(scale_build, max(repeats // 5, 3))
    rows.append({"case": "scale_build", "segments": len(sc_wps) - 1, "obstacles": len(boxes), "median_ms": med,
                 "min_ms": best})
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    rows = bench(args.repeats)
    for row in rows:
        extra = {k: (len(v) if isinstance(v, list) and len(v) > 8 else v) for k, v in row.items() if k not in ("case", "median_ms", "min_ms")}
        print(f"{row['case']:16s} median {row['median_ms']:7.2f} ms  min {row['min_ms']:7.2f} ms  {extra}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
