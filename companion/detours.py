"""Detours: waypoints inserted around an obstacle that blocks a straight leg.

When a leg's corridor cannot be built because an obstacle sits across it, the ways around
it (left, right, over, under; shortest first) are tried as one or two synthetic waypoints
(label -1) and the route is planned and verified again; up to MAX_DETOURS obstacles in turn.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from companion.config import Config
from companion.obstacles import Known, as_known
from companion.route import Outcome, build_corridors, plan_route
from companion.wire.messages import MissionSpec
from planner_core import (
    DEFAULT_MIN_DURATION,
    CorridorError,
    FloatArray,
    Polytope,
    corridor_cap,
    durations_from_lengths,
    polytope_vertices,
)


def plan_with_detours(
    mission: MissionSpec,
    points: FloatArray,
    times: FloatArray,
    labels: FloatArray,
    initial: FloatArray,
    obstacles: Known | Sequence[Polytope],
    cfg: Config,
    *,
    allocate: bool = False,
    neighbours: Any = None,
    candidates: int | None = None,
) -> Outcome:
    """plan_route, inserting detour points around obstacles that block straight legs
    (`allocate`, `candidates`: as plan_route's, for every attempt).

    Up to MAX_DETOURS obstacles are detoured, one after the other. A detoured plan is
    verified like any other (plan_route); its stats carry "detour" (the points) and
    "detour_obstacles", and `obstacle` names the first obstacle detoured around. A failure
    keeps `obstacle` (and `blocked_segment`) of the obstacle that could not be passed, as an
    index into `obstacles`, and its message says why each way around it failed.
    """
    known = as_known(obstacles)
    outcome = plan_route(mission, points, times, labels, initial, known, cfg, allocate=allocate, candidates=candidates,
                         neighbours=neighbours)
    detours: list[Any] = []
    around: list[int] = []
    for _ in range(MAX_DETOURS):
        if outcome.ok or outcome.blocked_segment is None or outcome.obstacle is None:
            break
        notes: list[str] = []
        detoured = detour(mission, points, times, labels, initial, known, cfg,
                          outcome.blocked_segment, outcome.obstacle, notes=notes, allocate=allocate, candidates=candidates,
                          neighbours=neighbours)
        if detoured is None:
            why = "; ".join(notes) or "no way around it inside the map"
            outcome = replace(outcome, message=f"{outcome.message}; no detour around {known.name(outcome.obstacle)} "
                              f"({why})")
            break
        around.append(int(outcome.obstacle or 0))  # not None: the loop's condition
        outcome, points, times, labels = detoured
        detours += outcome.stats.get("detour", [])
    else:
        if not outcome.ok and detours:
            outcome = replace(outcome, message=f"{outcome.message}; gave up after {MAX_DETOURS} detours")
    if outcome.ok and detours:
        outcome.stats["detour"] = detours
        outcome.stats["detour_obstacles"] = around
        outcome = replace(outcome, obstacle=around[0])
    return outcome


MAX_DETOURS = 3
DETOUR_MARGIN = 0.3


def _detour_options(a: FloatArray, b: FloatArray, obstacle: Polytope, radius: float) -> list[tuple[str, FloatArray]]:
    """(name, points) of each way around `obstacle` across a -> b, shortest first (see detour_candidates)."""
    verts = polytope_vertices(obstacle)
    length = float(np.linalg.norm(b - a))
    d = (b - a) / max(length, 1e-9)
    side = np.cross(d, [0.0, 0.0, 1.0])
    if np.linalg.norm(side) < 1e-6:  # a vertical path: any horizontal direction will do
        side = np.array([1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    up = np.cross(side, d)  # NED: z is down, so `up` points towards -z for a level leg
    clear = 2.0 * radius + DETOUR_MARGIN
    along = (verts - a) @ d
    # abreast of the near and far faces, `clear` beyond them; behind a or past b when the
    # obstacle is that close to them (every leg then keeps `clear` from it)
    near, far = float(along.min()) - clear, float(along.max()) + clear
    out = []
    for name, n in (("left", side), ("right", -side), ("over", up), ("under", -up)):
        lateral = float(np.max((verts - a) @ n)) + clear
        out.append((name, np.array([a + n * lateral + d * s for s in (near, far)])))
    return sorted(out, key=lambda o: float(np.sum(np.linalg.norm(np.diff(np.vstack([a, o[1], b]), axis=0), axis=1))))


def detour_candidates(a: FloatArray, b: FloatArray, obstacle: Polytope, radius: float) -> list[FloatArray]:
    """Ways around an obstacle that sits across the straight path a -> b: left, right, over
    and under it. Each is two points abreast of the obstacle's near and far faces, two radii
    plus a margin clear of it (so every leg a -> near -> far -> b keeps that clearance);
    shortest detour first."""
    return [pts for _, pts in _detour_options(a, b, obstacle, radius)]


def _detour_times(
    mission: MissionSpec,
    points: FloatArray,
    times: FloatArray,
    pts: FloatArray,
    segment: int,
    k: int,
    initial: FloatArray,
    first_corridor: Polytope | None,
) -> FloatArray:
    """Times for `pts` (= `points` with k detour points after `segment`).

    The detour legs get the allocation rule's durations (planner_core.timing, from the
    jet at pts[0], with the slower junctions of the turns); the legs before them and the
    one after never get less than that either (the vehicle must slow down for the turns),
    later legs keep theirs. With a moving start, the first leg is capped where the
    points fixed by the start jet would leave its corridor (timing rule 8).
    """
    old = np.diff(times)
    alloc = durations_from_lengths(pts, mission.bounds, initial_jet=initial)
    d = alloc.copy()
    d[:segment] = old[:segment]
    d[segment + k + 1 :] = old[segment + 1 :]
    after = segment + k + 1
    if after < len(d):
        d[after] = max(old[segment + 1], alloc[after])
    if first_corridor is not None and np.any(initial[1:]):
        d[0] = corridor_cap(initial, first_corridor, float(d[0]), DEFAULT_MIN_DURATION)
    return np.asarray(times[0] + np.concatenate([[0.0], np.cumsum(d)]), dtype=float)


def detour(
    mission: MissionSpec,
    points: FloatArray,
    times: FloatArray,
    labels: FloatArray,
    initial: FloatArray,
    obstacles: Known | Sequence[Polytope],
    cfg: Config,
    segment: int,
    obstacle: int,
    notes: list[str] | None = None,
    allocate: bool = False,
    neighbours: Any = None,
    candidates: int | None = None,
) -> tuple[Outcome, FloatArray, FloatArray, FloatArray] | None:
    """Insert synthetic waypoints around the obstacle that blocks `segment` and re-plan.

    Candidates (left, right, over, under; shortest first) are clipped to the map box
    shrunk by the radius, checked for corridors (cheap) and then planned and verified; the
    first verified plan wins. None if none plans; then, and only then, a candidate that
    clears this obstacle but is blocked by another one further on is returned (not ok),
    for the caller to detour that one too. `notes` collects why each candidate failed.
    """
    notes = [] if notes is None else notes
    known = as_known(obstacles)
    polys = known.polytopes
    if not 0 <= obstacle < len(polys) or not 0 <= segment < len(points) - 1:
        notes.append(f"internal: segment {segment} / obstacle {obstacle} out of range")
        return None
    a, b = points[segment], points[segment + 1]
    lo, hi = mission.corridor_map[0] + mission.radius, mission.corridor_map[1] - mission.radius
    best: tuple[Outcome, FloatArray, FloatArray, FloatArray] | None = None
    for name, cs in _detour_options(a, b, polys[obstacle], mission.radius):
        clipped = np.clip(cs, lo + 1e-6, hi - 1e-6)
        if np.max(np.abs(clipped - cs)) > DETOUR_MARGIN:
            notes.append(f"{name}: outside the map")
            continue
        cs = clipped
        k = len(cs)
        pts = np.insert(points, segment + 1, cs, axis=0)
        lab = np.insert(labels, segment + 1, np.full(k, -1.0))
        try:
            corridors = build_corridors(pts, polys, mission)
        except CorridorError as exc:
            seg = getattr(exc, "segment", None)
            if seg is not None and seg > segment + k and best is None:
                # this obstacle is cleared; another one blocks a later leg
                tms = _detour_times(mission, points, times, pts, segment, k, initial, None)
                outcome = plan_route(mission, pts, tms, lab, initial, known, cfg, allocate=allocate, candidates=candidates,
                                     neighbours=neighbours)
                outcome.stats["detour"] = [c.round(3).tolist() for c in cs]
                best = (outcome, pts, tms, lab)
            else:
                notes.append(f"{name}: {exc}")
            continue
        except Exception as exc:  # a geometry bug must be a refusal, not a crash
            notes.append(f"{name}: corridor construction failed: {exc!r}")
            continue
        tms = _detour_times(mission, points, times, pts, segment, k, initial, corridors[0])
        outcome = plan_route(mission, pts, tms, lab, initial, known, cfg, allocate=allocate, candidates=candidates,
                                     neighbours=neighbours)
        if outcome.ok:
            outcome.stats["detour"] = [c.round(3).tolist() for c in cs]
            return outcome, pts, tms, lab
        notes.append(f"{name}: {outcome.message}")
    return best
