"""Corridors that scale (the analysis box as broad phase, batched facets) and the local recovery.

The broad phase may choose other planes than considering every obstacle would, so corridors are
compared by what they promise (containment of the segment, a single-plane certificate for every
obstacle, the region near the segment), never bit for bit.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np
import pytest

from planner_core import Bounds, Polytope, Problem, plan, verify
from planner_core.broadphase import DENSE_PAIRS, count_beyond, overlapping_pairs
from planner_core.facets import facet_masks
from planner_core.geometry import (
    analysis_boxes,
    build_corridors,
    exclusion_margin,
    polytope_from_box,
    polytope_vertices,
    segment_clearance,
    update_corridors,
)
from planner_core.geometry.polytopes import enumerate_vertices as _vertices
from planner_core.geometry.pruning import _facet_mask

R = 0.3


# --- building blocks ---------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_overlapping_pairs_are_exactly_the_overlapping_boxes(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, q = 300, 60
    assert n * q > DENSE_PAIRS  # the sweep, not the dense test
    olo = rng.uniform(0.0, 100.0, (n, 3))
    ohi = olo + rng.uniform(0.1, 3.0, (n, 3))
    ohi[:5, 0] += 60.0  # a few wide boxes, tested apart
    qlo = rng.uniform(0.0, 100.0, (q, 3))
    qhi = qlo + rng.uniform(0.0, 15.0, (q, 3))
    qi, ok = overlapping_pairs(qlo, qhi, olo, ohi)
    ref = np.all((olo[None] < qhi[:, None]) & (ohi[None] > qlo[:, None]), axis=2)
    assert np.array_equal(np.stack(np.nonzero(ref)), np.stack([qi, ok]))
    t = rng.uniform(0.0, 100.0, 20)
    assert np.array_equal(count_beyond(olo[:, 1], t, upper=True), (olo[None, :, 1] >= t[:, None]).sum(axis=1))
    assert np.array_equal(count_beyond(ohi[:, 1], t, upper=False), (ohi[None, :, 1] <= t[:, None]).sum(axis=1))


def test_batched_facets_agree_with_one_polytope_at_a_time() -> None:
    rng = np.random.default_rng(3)
    eye = np.eye(3)
    As, bs = [], []
    for _ in range(40):
        n = rng.normal(size=(5, 3))
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        # a box cut by 5 planes at random depths (some cut nothing, some a corner, some twice the same)
        n[4] = n[3]
        b = np.concatenate([np.full(6, 2.0), rng.uniform(0.3, 4.0, 5)])
        As.append(np.concatenate([eye, -eye, n]))
        bs.append(b)
    A, b = np.stack(As), np.stack(bs)
    got = facet_masks(A, b)
    for g in range(A.shape[0]):
        verts = _vertices(A[g], b[g])
        assert np.array_equal(got[g], _facet_mask(A[g], b[g], verts)), g


# --- scenes ------------------------------------------------------------------------------


def scene(seed: int, m: int, n_obs: int, spread: float) -> tuple[np.ndarray, list[Polytope], tuple[np.ndarray, np.ndarray]]:
    """A waypoint walk with boxes scattered over a map `spread` wide; boxes that would block a
    leg or swallow a waypoint are dropped (tested one at a time)."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=(m - 1, 3)) * [1.0, 1.0, 0.2]
    steps *= rng.uniform(2.0, 5.0, (m - 1, 1)) / np.linalg.norm(steps, axis=1, keepdims=True)
    wps = np.cumsum(np.vstack([np.zeros(3), steps]), axis=0) + np.array([spread / 2, spread / 2, 4.0])
    lo, hi = np.minimum(wps.min(0) - 10.0, 0.0), np.maximum(wps.max(0) + 10.0, [spread, spread, 8.0])
    lo[2], hi[2] = min(lo[2], 0.0), max(hi[2], 8.0)
    box = (lo, hi)
    obs = []
    for _ in range(n_obs):
        cand = polytope_from_box(rng.uniform(lo, hi), rng.uniform(0.3, 3.0, 3))
        try:
            build_corridors(wps, [cand], box, R)
        except ValueError:
            continue
        obs.append(cand)
    return wps, obs, box


def assert_valid(corridor: Polytope, p0: np.ndarray, p1: np.ndarray, obs: list[Polytope],
                 box: tuple[np.ndarray, np.ndarray]) -> None:
    assert segment_clearance(p0, p1, corridor) >= -1e-9  # the map faces may touch the segment
    map_lo, map_hi = box[0] + R, box[1] - R
    inner = np.concatenate([np.eye(3), -np.eye(3)])
    for a, b in zip(corridor.A, corridor.b, strict=True):
        on_map = np.any(np.all(np.isclose(inner, a), axis=1)) and np.any(np.isclose(np.concatenate([map_hi, -map_lo]), b))
        if not on_map:
            assert float(b - max(a @ p0, a @ p1)) >= R - 1e-9
    for o in obs:
        assert exclusion_margin(corridor, polytope_vertices(o)) >= R - 1e-9


def inside(corridor: Polytope, pts: np.ndarray, slack: float) -> np.ndarray:
    return np.all(pts @ corridor.A.T <= corridor.b + slack, axis=1)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_broad_phase_corridors_keep_every_promise_of_the_full_ones(seed: int) -> None:
    """Without the broad phase (an analysis box holding the whole map: every obstacle a candidate,
    as every obstacle was considered before it) the corridors keep the same promises and, near
    the segment, the same region."""
    wps, obs, box = scene(seed, 10, 60, 60.0)
    fast = build_corridors(wps, obs, box, R)
    full = build_corridors(wps, obs, box, R, influence=1e4)
    rng = np.random.default_rng(seed)
    for j in range(len(wps) - 1):
        assert_valid(fast[j], wps[j], wps[j + 1], obs, box)
        assert_valid(full[j], wps[j], wps[j + 1], obs, box)
        # near the segment both leave the same room: the planes of the obstacles that matter
        # are the same maximum-margin planes (farther ones are box faces instead)
        t = rng.uniform(0.0, 1.0, (400, 1))
        pts = wps[j] + t * (wps[j + 1] - wps[j]) + rng.normal(size=(400, 3)) * 0.7
        near_fast = inside(fast[j], pts, 1e-9)
        near_full = inside(full[j], pts, 1e-9)
        assert np.mean(near_fast == near_full) > 0.99


@pytest.mark.parametrize("seed", [0, 1])
def test_far_obstacles_never_change_a_corridor(seed: int) -> None:
    wps, obs, box = scene(seed, 8, 25, 40.0)
    # boxes beyond every segment's analysis box (by more than the radius), wherever the map has room
    p0, p1 = wps[:-1], wps[1:]
    flo, fhi = analysis_boxes(p0, p1, np.linalg.norm(p1 - p0, axis=1) + 3.0, box, R)
    rng = np.random.default_rng(seed)
    big = (box[0] - 200.0, box[1] + 200.0)
    far: list[Polytope] = []
    while len(far) < 30:
        c = rng.uniform(big[0], big[1])
        if np.all(np.any((c - 1.0 > fhi + R) | (c + 1.0 < flo - R), axis=1)):
            far.append(polytope_from_box(c, [2.0, 2.0, 2.0]))
    after = build_corridors(wps, [*obs, *far], big, R)
    again = build_corridors(wps, obs, big, R)
    pts = rng.uniform(big[0], big[1], (4000, 3))
    for j in range(len(wps) - 1):
        assert_valid(after[j], wps[j], wps[j + 1], [*obs, *far], big)
        # the same region (a box face may be kept as the far obstacles' certificate, and that
        # face is no facet), the same planes apart from faces
        assert np.array_equal(inside(after[j], pts, 1e-9), inside(again[j], pts, 1e-9))
        own = np.count_nonzero(after[j].A, axis=1) > 1
        assert np.array_equal(after[j].A[own], again[j].A[np.count_nonzero(again[j].A, axis=1) > 1])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_popup_update_agrees_with_a_rebuild(seed: int) -> None:
    wps, obs, box = scene(seed, 10, 40, 40.0)
    old, new = obs[: len(obs) // 2], obs[len(obs) // 2 :]
    before = build_corridors(wps, old, box, R)
    updated, changed = update_corridors(wps, before, old, new, box, R, prune=False)
    rebuilt = build_corridors(wps, [*old, *new], box, R)
    rng = np.random.default_rng(seed)
    for j in range(len(wps) - 1):
        assert_valid(updated[j], wps[j], wps[j + 1], [*old, *new], box)
        certified = all(exclusion_margin(before[j], polytope_vertices(o)) >= R - 1e-10 for o in new)
        assert (j in changed) == (not certified)
        lo, hi = np.minimum(wps[j], wps[j + 1]) - 6.0, np.maximum(wps[j], wps[j + 1]) + 6.0
        pts = rng.uniform(lo, hi, (3000, 3))
        # the rebuild has a plane for every new candidate, the update only where no plane already
        # kept it away: the update's region holds the rebuild's
        assert not np.any(inside(rebuilt[j], pts, -1e-7) & ~inside(updated[j], pts, 1e-7))


# --- local recovery ----------------------------------------------------------------------


def tight_mission(m: int = 40, tight: int = 20, factor: float = 0.3) -> Problem:
    rng = np.random.default_rng(5)
    steps = rng.normal(size=(m - 1, 3)) * [1.0, 1.0, 0.3]
    steps *= rng.uniform(2.0, 5.0, (m - 1, 1)) / np.linalg.norm(steps, axis=1, keepdims=True)
    wps = np.cumsum(np.vstack([np.zeros(3), steps]), axis=0)
    durations = np.linalg.norm(steps, axis=1) / 2.5 + 0.8
    durations[tight] *= factor
    eye = np.eye(3)
    cors = tuple(
        Polytope(np.concatenate([eye, -eye]),
                 np.concatenate([np.maximum(wps[i], wps[i + 1]) + 1.0, -(np.minimum(wps[i], wps[i + 1]) - 1.0)]))
        for i in range(m - 1)
    )
    return Problem.from_waypoints(wps, durations, Bounds.symmetric(4.0, 4.0, 12.0, 40.0), cors)


@pytest.mark.parametrize("compiled", [True, False])
def test_a_recovery_stretches_only_around_the_tight_segment_and_verifies(compiled: bool) -> None:
    problem = tight_mission()
    res = plan(problem, compiled=compiled)
    assert res.ok and res.trajectory is not None, res.message
    assert "duration_scale" not in res.stats  # no uniform search was needed
    recs = res.stats["recoveries"]
    assert recs and all(r.get("local") for r in recs)
    new = np.diff(res.trajectory.times)
    changed = np.flatnonzero(np.abs(new / problem.durations - 1.0) > 1e-9)
    assert changed.size and 20 in changed.tolist()
    window = res.stats["window"]
    assert changed.min() >= 20 - window - 1 and changed.max() <= 20 + window + 1  # local
    stretched = {d["segment"] for d in res.stats["stretched_durations"]}
    assert stretched == set(changed.tolist())
    assert verify(res.trajectory, Problem(problem.waypoints, res.trajectory.times, problem.bounds,
                                          problem.initial, problem.final, problem.corridors)).ok


def test_without_recovery_the_tight_mission_is_diagnosed() -> None:
    problem = tight_mission()
    res = plan(problem, recover=False)
    assert not res.ok and res.diagnosis is not None
    assert res.diagnosis.min_scale is not None and res.diagnosis.min_scale > 1.0


def test_triples_are_the_index_combinations() -> None:
    from planner_core.facets import triples

    assert triples(6).tolist() == [list(t) for t in combinations(range(6), 3)]


def test_dense_clutter_keeps_every_promise() -> None:
    """Many candidates per segment: the greedy rule and the certificate restoration at work."""
    rng = np.random.default_rng(11)
    wps = np.array([[2.0, 2.0, 2.0], [8.0, 3.0, 2.5], [12.0, 8.0, 2.0], [6.0, 12.0, 3.0]])
    box = (np.zeros(3), np.array([15.0, 15.0, 6.0]))
    obs = []
    for c in rng.uniform(box[0], box[1], (400, 3)):
        cand = polytope_from_box(c, rng.uniform(0.2, 0.6, 3))
        try:
            build_corridors(wps, [cand], box, R)
        except ValueError:
            continue
        obs.append(cand)
    assert len(obs) > 200
    corridors = build_corridors(wps, obs, box, R)
    for j, c in enumerate(corridors):
        assert_valid(c, wps[j], wps[j + 1], obs, box)
        assert c.b.size < 40  # the obstacles behind nearer planes took none of their own


def test_short_windows_retry_before_stretching() -> None:
    """The paper's one-jet window dead-ends on this scene: a wider or earlier window (no time
    added) settles it, as the retries do, on the local piece."""
    from tests.planner.test_window import _problem

    problem = _problem(3, 14)
    res = plan(problem, window=1)
    assert res.ok and res.trajectory is not None
    recs = res.stats["recoveries"]
    assert recs and all(r["action"] == "backtrack/widen" and r.get("local") for r in recs)
    assert res.stats["stretched_durations"] == []
    assert np.array_equal(res.trajectory.times, problem.times)


def test_when_no_stretch_helps_the_fallback_diagnoses() -> None:
    """Starting above the velocity bound: no local stretch (nor the whole-mission fallback) can
    help; the plan fails with a diagnosis instead of looping."""
    problem = tight_mission(m=8, tight=3, factor=1.0)
    init = problem.initial.copy()
    init[1, 0] = 6.0  # over the 4 m/s bound at t = 0
    bad = Problem(problem.waypoints, problem.times, problem.bounds, init, problem.final, problem.corridors)
    res = plan(bad)
    assert not res.ok and res.diagnosis is not None
    assert res.stats["recoveries"][-1]["action"] == "failed"
