"""Batched separation (closest pair instead of one SVM QP per pair) and the vectorised
in-flight update (every affected corridor at once)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from planner_core.geometry import (
    CorridorError,
    build_corridors,
    exclusion_margin,
    normalised,
    polytope_from_box,
    polytope_vertices,
    separation,
    separations,
    update_corridors,
)
from planner_core.geometry.building import add_planes as _add_planes
from planner_core.geometry.building import build_context as _context
from planner_core.geometry.building import check_waypoints_clear as _check_waypoints_clear
from planner_core.geometry.obstacles import prepare_obstacles as _prepare_obstacles
from planner_core.geometry.obstacles import segment_point_distance as _segment_point_distance
from planner_core.geometry.pruning import _first_of_duplicates
from planner_core.problem import Polytope
from tests.planner.test_corridors import FAST, dist_segment_polytope, random_obstacle, random_scene

# --- separations ------------------------------------------------------------------


def _segments(rng: np.random.Generator, centre: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    p0 = centre + rng.normal(size=(n, 3)) * 3.0
    p1 = p0 + rng.normal(size=(n, 3)) * rng.uniform(0.0, 4.0, size=(n, 1))
    p1[: n // 5] = p0[: n // 5]  # some are points
    return p0, p1


@FAST
@given(seed=st.integers(0, 2**32 - 1))
def test_separations_match_the_svm_and_the_distance(seed: int) -> None:
    rng = np.random.default_rng(seed)
    centre = rng.normal(size=3) * 3
    obstacle = random_obstacle(rng, centre)
    verts = polytope_vertices(obstacle)
    A, b = normalised(obstacle)
    p0, p1 = _segments(rng, centre, 12)
    normals, gaps = separations(p0, p1, verts, A, b)
    for i in range(p0.shape[0]):
        seg = np.stack([p0[i], p1[i]])
        svm_normal, svm_gap = separation(seg, verts)
        if np.isnan(normals[i, 0]):
            assert gaps[i] == 0.0
            assert svm_normal is None or svm_gap <= 1e-9  # they meet (or touch)
            assert dist_segment_polytope(p0[i], p1[i], obstacle) <= 1e-6
            continue
        n = normals[i]
        assert np.linalg.norm(n) == pytest.approx(1.0, abs=1e-12)
        # the gap is the slab this normal leaves, the distance of the two sets, at least the SVM's
        assert gaps[i] == pytest.approx(float(np.min(verts @ n) - np.max(seg @ n)), abs=1e-12)
        assert gaps[i] > 0.0
        assert gaps[i] >= svm_gap - 1e-9
        assert gaps[i] == pytest.approx(dist_segment_polytope(p0[i], p1[i], obstacle), abs=1e-6)


def test_separations_special_positions() -> None:
    box = polytope_from_box([0.0, 0.0, 0.0], [2.0, 2.0, 2.0])
    verts = polytope_vertices(box)
    A, b = normalised(box)
    p0 = np.array([
        [-3.0, 0.0, 0.0],  # crosses the box
        [-3.0, 2.0, 0.5],  # parallel to the +y face, 1 away: the face's normal
        [2.0, 2.0, 2.0],  # a point off a corner
        [3.0, -5.0, 0.0],  # skew to an edge of the box
        [0.5, 0.5, 1.0],  # starts on the top face: touching
    ])
    p1 = np.array([
        [3.0, 0.0, 0.0],
        [3.0, 2.0, 0.5],
        [2.0, 2.0, 2.0],
        [3.0, 5.0, 0.0],
        [0.5, 0.5, 4.0],
    ])
    normals, gaps = separations(p0, p1, verts, A, b)
    assert np.isnan(normals[0, 0]) and gaps[0] == 0.0
    assert normals[1] == pytest.approx([0.0, -1.0, 0.0], abs=1e-12) and gaps[1] == pytest.approx(1.0)
    assert normals[2] == pytest.approx(-np.ones(3) / np.sqrt(3.0)) and gaps[2] == pytest.approx(np.sqrt(3.0))
    assert normals[3] == pytest.approx([-1.0, 0.0, 0.0], abs=1e-12) and gaps[3] == pytest.approx(2.0)
    assert np.isnan(normals[4, 0]) and gaps[4] == 0.0
    assert separations(np.zeros((0, 3)), np.zeros((0, 3)), verts, A, b)[0].shape == (0, 3)


# --- the in-flight update -----------------------------------------------------------


def sequential_update(
    wps: np.ndarray, before: tuple[Polytope, ...], old: list[Polytope], new: list[Polytope], r: float
) -> tuple[list[Polytope], list[int]]:
    """update_corridors(prune=False) one corridor at a time, as it was written before batching."""
    obs = _prepare_obstacles(new, first_index=len(old))
    ctx = _context(wps, obs, None, r, first_index=len(old))
    _check_waypoints_clear(ctx)
    lower = np.maximum(_segment_point_distance(wps[:-1], wps[1:], obs.centres) - obs.radii, 0.0)
    out, changed = list(before), []
    for j, corridor in enumerate(before):
        A, b = normalised(corridor)
        if obs.n == 0 or np.all(np.any(obs.margins(A, b) >= r - 1e-10, axis=1)):
            continue
        A2, b2 = _add_planes(ctx, j, A, b, np.argsort(lower[j], kind="stable"), np.zeros(obs.n, dtype=bool))
        keep = _first_of_duplicates(A2, b2)
        out[j] = Polytope(A2[keep], b2[keep])
        changed.append(j)
    return out, changed


def popup_scene(seed: int, m: int, r: float) -> tuple[np.ndarray, list[Polytope], list[Polytope], tuple[np.ndarray, np.ndarray]]:
    """Known obstacles cleared of the route, pop-ups anywhere near it (they may block)."""
    wps, obs, box = random_scene(seed, m, 6)
    rng = np.random.default_rng(seed + 1)
    old = [o for o in obs if all(dist_segment_polytope(wps[j], wps[j + 1], o, 2 * r + 1) >= 2 * r + 1e-3 for j in range(m - 1))]
    new = []
    for _ in range(int(rng.integers(1, 5))):
        j = int(rng.integers(0, m - 1))
        centre = wps[j] + rng.random() * (wps[j + 1] - wps[j]) + rng.normal(size=3) * 1.5
        new.append(random_obstacle(rng, centre))
    return wps, old, new, box


@settings(FAST, max_examples=30)
@given(seed=st.integers(0, 2**32 - 1), m=st.integers(2, 8), r=st.sampled_from([0.0, 0.1, 0.3]), use_map=st.booleans())
def test_fast_update_equals_the_sequential_one(seed: int, m: int, r: float, use_map: bool) -> None:
    wps, old, new, box = popup_scene(seed, m, r)
    map_box = box if use_map else None
    before = build_corridors(wps, old, map_box, r)
    try:
        ref, ref_changed = sequential_update(wps, before, old, new, r)
    except CorridorError as exc:
        # the same first blocked (segment, obstacle) as the corridor-by-corridor loop
        with pytest.raises(CorridorError) as info:
            update_corridors(wps, before, old, new, map_box, r, prune=False)
        assert (info.value.segment, info.value.obstacle, info.value.waypoint) == (exc.segment, exc.obstacle, exc.waypoint)
        assert str(info.value) == str(exc)
        return
    fast, changed = update_corridors(wps, before, old, new, map_box, r, prune=False)
    assert changed == ref_changed
    for j in range(m - 1):
        if j not in changed:
            assert fast[j] is before[j]
            continue
        assert fast[j].A.shape == ref[j].A.shape
        assert np.allclose(fast[j].A, ref[j].A, rtol=0, atol=1e-12)
        assert np.allclose(fast[j].b, ref[j].b, rtol=0, atol=1e-12)
        assert float(np.max(wps[j : j + 2] @ fast[j].A.T - fast[j].b)) <= 1e-9
        for o in [*old, *new]:
            assert exclusion_margin(fast[j], polytope_vertices(o)) >= r - 1e-9


@settings(FAST, max_examples=10)
@given(seed=st.integers(0, 2**32 - 1))
def test_map_only_corridors_take_the_popup_where_it_matters(seed: int) -> None:
    """No known obstacles: the corridors whose analysis box does not already keep the pop-up r
    away get its plane (the others are left alone); with prune=False and prune=True alike,
    the region is the same."""
    rng = np.random.default_rng(seed)
    m = 40
    wps = np.cumsum(np.vstack([np.zeros(3), rng.normal(size=(m - 1, 3)) * [2.0, 2.0, 0.3]]), axis=0)
    box = (wps.min(axis=0) - 4.0, wps.max(axis=0) + 4.0)
    r = 0.3
    before = tuple(build_corridors(wps[j : j + 2], [], box, r)[0] for j in range(m - 1))
    j = int(rng.integers(0, m - 1))
    side = np.cross(wps[j + 1] - wps[j], [0.0, 0.0, 1.0])
    assume(np.linalg.norm(side) > 1e-3)
    popup = polytope_from_box(0.5 * (wps[j] + wps[j + 1]) + side / np.linalg.norm(side), [0.2, 0.2, 0.2])
    try:
        fast, changed = update_corridors(wps, before, [], [popup], box, r, prune=False)
    except CorridorError:
        with pytest.raises(CorridorError):
            update_corridors(wps, before, [], [popup], box, r)
        return
    pruned, changed_pruned = update_corridors(wps, before, [], [popup], box, r)
    verts = polytope_vertices(popup)
    uncertified = [k for k in range(m - 1) if exclusion_margin(before[k], verts) < r - 1e-10]
    assert j in uncertified
    assert changed == changed_pruned == uncertified
    pts = rng.uniform(box[0], box[1], size=(2000, 3))
    for k in range(m - 1):
        assert exclusion_margin(fast[k], verts) >= r - 1e-9
        assert float(np.max(wps[k : k + 2] @ fast[k].A.T - fast[k].b)) <= 1e-9
        inside_fast = np.all(pts @ fast[k].A.T <= fast[k].b + 1e-9, axis=1)
        inside_pruned = np.all(pts @ pruned[k].A.T <= pruned[k].b + 1e-9, axis=1)
        assert np.array_equal(inside_fast, inside_pruned)


@pytest.mark.parametrize("prune", [False, True])
@pytest.mark.parametrize(
    ("bad", "why"),
    [
        (Polytope(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), np.array([1.0, 1.0])), "row 1 of A is zero"),
        (Polytope(np.array([[1.0, 0.0, 0.0]]), np.array([np.nan])), "finite"),
        (Polytope(np.ones((2, 2)), np.ones(2)), "must be"),
    ],
)
def test_bad_corridor_is_named(prune: bool, bad: Polytope, why: str) -> None:
    wps = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [5.0, 5.0, 0.0], [10.0, 5.0, 0.0]])
    cors = list(build_corridors(wps, [], None, 0.3))
    cors[2] = bad
    with pytest.raises(ValueError, match=rf"corridors\[2\]: .*{why}"):
        update_corridors(wps, cors, [], [polytope_from_box([2.5, 3.0, 0.0], [1, 1, 1])], None, 0.3, prune=prune)
