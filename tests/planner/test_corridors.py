"""Safe corridors: containment, exclusion, blocking, pruning, room, updates, hulls.

Distances are checked against independent QPs (closest points in primal form,
solved by daqp), not against the SVM that planner_core.geometry uses.
"""

from __future__ import annotations

from itertools import combinations

import daqp
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from planner_core.geometry import (
    CorridorError,
    analysis_boxes,
    build_corridors,
    corridor_contains_segment,
    exclusion_margin,
    polytope_from_box,
    polytope_from_vertices,
    polytope_vertices,
    segment_clearance,
    update_corridors,
)
from planner_core.problem import Polytope

FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
BIG = (np.concatenate([np.eye(3), -np.eye(3)]), np.full(6, 1e3))
EDGE = 1e-6  # scenes within this of a decision threshold are skipped (either answer is right)


# --- independent geometry ---------------------------------------------------------


def _unit(poly: Polytope) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(poly.A, axis=1)
    return poly.A / n[:, None], poly.b / n


def _qp(H: np.ndarray, f: np.ndarray, A: np.ndarray, bu: np.ndarray, bl: np.ndarray) -> np.ndarray:
    x, _, flag, _ = daqp.solve(H, f, A, bu, bl, np.zeros(len(bu), dtype=np.int32))
    assert flag == 1, f"reference QP failed ({flag})"
    return np.asarray(x)


def dist_point_polytope(p: np.ndarray, poly: Polytope) -> float:
    A, b = _unit(poly)
    y = _qp(2.0 * np.eye(3), -2.0 * p, A, b, np.full(len(b), -1e30))
    return float(np.linalg.norm(y - p))


_VERTS: dict[int, tuple[Polytope, np.ndarray]] = {}


def verts_of(poly: Polytope) -> np.ndarray:
    """polytope_vertices, memoised per object (the scenes reuse obstacles a lot)."""
    hit = _VERTS.get(id(poly))
    if hit is None or hit[0] is not poly:
        hit = _VERTS[id(poly)] = (poly, polytope_vertices(poly))
    return hit[1]


def _sphere_lower_bound(p0: np.ndarray, p1: np.ndarray, poly: Polytope) -> float:
    """A cheap lower bound: distance to the obstacle's bounding sphere."""
    v = verts_of(poly)
    c = v.mean(axis=0)
    e = p1 - p0
    t = float(np.clip((c - p0) @ e / max(float(e @ e), 1e-300), 0.0, 1.0))
    return float(np.linalg.norm(p0 + t * e - c) - np.max(np.linalg.norm(v - c, axis=1)))


def dist_segment_polytope(p0: np.ndarray, p1: np.ndarray, poly: Polytope, upto: float = np.inf) -> float:
    """Exact distance by golden-section search (convex along the segment).

    Only exact below `upto`: when the bounding sphere is already that far, its
    (smaller) distance is returned instead.
    """
    A, b = _unit(poly)
    # a face plane with the whole segment beyond it also bounds the distance
    plane = float(np.max(np.minimum(A @ p0 - b, A @ p1 - b)))
    bound = max(_sphere_lower_bound(p0, p1, poly), plane)
    if bound >= upto:
        return bound
    lo, hi = 0.0, 1.0
    g = (np.sqrt(5.0) - 1.0) / 2.0
    for _ in range(40):
        a, b = hi - g * (hi - lo), lo + g * (hi - lo)
        if dist_point_polytope(p0 + a * (p1 - p0), poly) <= dist_point_polytope(p0 + b * (p1 - p0), poly):
            hi = b
        else:
            lo = a
    return min(dist_point_polytope(p0 + t * (p1 - p0), poly) for t in (0.0, (lo + hi) / 2, 1.0))


def dist_polytopes(P: Polytope, Q: Polytope, upto: float = np.inf, samples: int = 40) -> float:
    """Smallest distance from sampled points of Q (vertices, edge and random inner points) to P.

    An upper bound on the true distance (exact when the closest point of Q is
    sampled, e.g. a vertex), and only computed below `upto`: a plane of P with
    Q's bounding sphere that far beyond it gives a lower bound, returned instead.
    """
    v = verts_of(Q)
    c = v.mean(axis=0)
    A, b = _unit(P)
    bound = float(np.max(A @ c - b)) - float(np.max(np.linalg.norm(v - c, axis=1))) if len(b) else -np.inf
    if bound >= upto:
        return bound
    rng = np.random.default_rng(0)
    i, j = np.triu_indices(len(v), 1)
    inner = rng.dirichlet(np.full(len(v), 0.3), size=samples) @ v
    pts = np.concatenate([v, (v[i] + v[j]) / 2, inner])
    return min(dist_point_polytope(p, P) for p in pts)


def brute_vertices(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Every feasible intersection of three planes (duplicates kept)."""
    idx = np.array(list(combinations(range(len(b)), 3)))
    M = A[idx]
    ok = np.abs(np.linalg.det(M)) > 1e-10
    x = np.linalg.solve(M[ok], b[idx[ok]][..., None])[..., 0]
    return x[np.all(x @ A.T <= b + 1e-7, axis=1)]


# --- scenes -----------------------------------------------------------------------


def random_obstacle(rng: np.random.Generator, centre: np.ndarray) -> Polytope:
    if rng.random() < 0.5:
        return polytope_from_box(centre, rng.uniform(0.2, 2.0, 3))
    return polytope_from_vertices(centre + rng.normal(size=(int(rng.integers(4, 10)), 3)) * rng.uniform(0.2, 1.0))


def random_scene(seed: int, m: int, n_obs: int) -> tuple[np.ndarray, list[Polytope], tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=(m - 1, 3))
    steps *= rng.uniform(1.0, 6.0, (m - 1, 1)) / np.linalg.norm(steps, axis=1)[:, None]
    wps = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
    obs = []
    for _ in range(n_obs):
        j = int(rng.integers(0, m - 1))
        centre = wps[j] + rng.random() * (wps[j + 1] - wps[j]) + rng.normal(size=3) * 1.5
        obs.append(random_obstacle(rng, centre))
    pts = np.concatenate([wps, *[verts_of(o) for o in obs]]) if obs else wps
    return wps, obs, (pts.min(axis=0) - 2.0, pts.max(axis=0) + 2.0)


def clear_obstacles(wps: np.ndarray, obs: list[Polytope], r: float) -> list[Polytope]:
    """Obstacles that leave every segment a gap of at least 2r (with a margin)."""
    return [
        o for o in obs
        if all(dist_segment_polytope(wps[j], wps[j + 1], o, 2 * r + 1) >= 2 * r + 1e-3 for j in range(len(wps) - 1))
    ]


def split_scene(
    seed: int, m: int, r: float, use_map: bool
) -> tuple[np.ndarray, list[Polytope], list[Polytope], tuple[np.ndarray, np.ndarray] | None]:
    """A clear random scene whose obstacles are split into known ones and new (pop-up) ones."""
    wps, obs, box = random_scene(seed, m, 8)
    obs = clear_obstacles(wps, obs, r)
    assume(len(obs) >= 2)
    return wps, obs[: len(obs) // 2], obs[len(obs) // 2 :], (box if use_map else None)


def map_faces(map_box: tuple[np.ndarray, np.ndarray] | None, r: float) -> tuple[np.ndarray, np.ndarray]:
    if map_box is None:
        return np.zeros((0, 3)), np.zeros(0)
    eye = np.eye(3)
    return np.concatenate([eye, -eye]), np.concatenate([map_box[1] - r, -(map_box[0] + r)])


def is_map_face(a: np.ndarray, b: float, faces: tuple[np.ndarray, np.ndarray]) -> bool:
    A, B = faces
    return bool(np.any(np.all(np.abs(A - a) < 1e-9, axis=1) & (np.abs(B - b) < 1e-9)))


def check_corridor(
    corridor: Polytope,
    p0: np.ndarray,
    p1: np.ndarray,
    obs: list[Polytope],
    r: float,
    map_box: tuple[np.ndarray, np.ndarray] | None,
) -> None:
    A, b = _unit(corridor)
    assert np.allclose(np.linalg.norm(corridor.A, axis=1), 1.0)
    faces = map_faces(map_box, r)
    samples = p0 + np.linspace(0.0, 1.0, 21)[:, None] * (p1 - p0)
    room = b[None, :] - samples @ A.T  # (21, P)
    for p in range(len(b)):
        need = 0.0 if is_map_face(A[p], b[p], faces) else r
        assert room[:, p].min() >= need - 1e-9, f"plane {p} leaves the segment {room[:, p].min()} < {need}"
    verts = [verts_of(o) for o in obs]
    for k, v in enumerate(verts):
        assert exclusion_margin(corridor, v) >= r - 1e-9, f"obstacle {k} has no single-plane certificate"
    # no useless plane: every plane either shapes the region or certifies some obstacle (a face
    # of the analysis box certifies every obstacle beyond it, so it need not be the only one)
    for p in range(len(b)):
        rest = np.delete(np.arange(len(b)), p)
        # judge inside a box far larger than the scene
        region = brute_vertices(np.concatenate([A[rest], BIG[0]]), np.concatenate([b[rest], BIG[1]]))
        shapes = region.size > 0 and float(np.max(region @ A[p])) > b[p] + 1e-7
        certifies = any(float(np.min(vv @ A[p] - b[p])) >= r - 1e-9 for vv in verts)
        assert shapes or certifies, f"plane {p} is redundant"


# --- hull ---------------------------------------------------------------------------


@FAST
@given(seed=st.integers(0, 2**32 - 1), k=st.integers(4, 25), scale=st.floats(0.01, 1000.0))
def test_hull_round_trip(seed: int, k: int, scale: float) -> None:
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(k, 3)) * scale + rng.normal(size=3) * scale
    assume(np.linalg.svd(pts - pts.mean(0), compute_uv=False)[2] > 1e-3 * scale)
    hull = polytope_from_vertices(pts)
    A, b = hull.A, hull.b
    assert np.allclose(np.linalg.norm(A, axis=1), 1.0)
    s = pts @ A.T - b
    assert s.max() <= 1e-9 * scale, "a vertex lies outside the hull"
    on = np.abs(s) <= 1e-7 * scale
    assert np.all(on.sum(axis=0) >= 3), "a face passes through fewer than 3 vertices"
    # no duplicated faces, and every hull corner is one of the input points
    assert not np.any(np.tril(np.abs(A @ A.T - 1.0) < 1e-9, -1) & np.tril(np.abs(b[:, None] - b[None, :]) < 1e-7 * scale, -1))
    corners = polytope_vertices(hull)
    d = np.min(np.linalg.norm(corners[:, None, :] - pts[None, :, :], axis=-1), axis=1)
    assert d.max() <= 1e-6 * scale


def test_hull_of_cube_has_six_faces() -> None:
    cube = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
    inner = np.array([[0.5, 0.5, 0.5], [0.2, 0.3, 0.4]])
    hull = polytope_from_vertices(np.concatenate([cube, inner, cube[:2]]))
    assert hull.A.shape == (6, 3)
    assert hull.contains(inner).all() and not hull.contains(np.array([[1.1, 0.5, 0.5]])).any()


@pytest.mark.parametrize(
    ("points", "why"),
    [
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], "at least 4"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 3, 0]], "coplanar"),
        ([[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]], "collinear"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, float("nan")]], "non-finite"),
        ([[1, 1, 1]] * 5, "coincide"),
        ([[0, 0], [1, 0], [0, 1], [1, 1]], "shape"),
    ],
)
def test_hull_rejects_degenerate_input(points: list[list[float]], why: str) -> None:
    with pytest.raises(ValueError, match=why):
        polytope_from_vertices(np.array(points, dtype=float))


def test_box_and_vertices() -> None:
    box = polytope_from_box([1.0, 2.0, 3.0], [2.0, 4.0, 6.0])
    v = polytope_vertices(box)
    assert v.shape == (8, 3)
    assert np.allclose(np.sort(np.unique(v[:, 1])), [0.0, 4.0])
    with pytest.raises(ValueError, match="size"):
        polytope_from_box([0, 0, 0], [1.0, 0.0, 1.0])
    half = Polytope(A=np.array([[0.0, 0.0, 1.0]]), b=np.array([0.0]))
    with pytest.raises(ValueError, match="unbounded"):
        polytope_vertices(half)
    empty = Polytope(A=np.concatenate([np.eye(3), -np.eye(3)]), b=np.array([0, 0, 0, -1.0, 0, 0]))
    with pytest.raises(ValueError, match="empty"):
        polytope_vertices(empty)


def test_segment_clearance() -> None:
    box = polytope_from_box([0, 0, 0], [4, 4, 4])
    assert segment_clearance([-1, 0, 0], [1, 0.5, 0], box) == pytest.approx(1.0)
    assert corridor_contains_segment([-1, 0, 0], [1, 0.5, 0], box, radius=1.0)
    assert not corridor_contains_segment([-1, 0, 0], [1, 0.5, 0], box, radius=1.1)
    assert segment_clearance([0, 0, 0], [3, 0, 0], box) == pytest.approx(-1.0)


# --- corridors ---------------------------------------------------------------------


@settings(FAST, max_examples=20)
@given(
    seed=st.integers(0, 2**32 - 1),
    m=st.integers(2, 6),
    n_obs=st.integers(0, 8),
    r=st.sampled_from([0.0, 0.1, 0.3, 0.5]),
    use_map=st.booleans(),
    influence=st.sampled_from([None, 0.0, 4.0]),
)
def test_corridors_contain_segments_and_exclude_obstacles(
    seed: int, m: int, n_obs: int, r: float, use_map: bool, influence: float | None
) -> None:
    wps, obs, box = random_scene(seed, m, n_obs)
    obs = clear_obstacles(wps, obs, r)
    map_box = (box[0] - r, box[1] + r) if use_map else None
    corridors = build_corridors(wps, obs, map_box, r, influence=influence)
    assert len(corridors) == m - 1
    for j, c in enumerate(corridors):
        check_corridor(c, wps[j], wps[j + 1], obs, r, map_box)
        for o in obs:  # independent exclusion check: inflated obstacle misses the corridor
            assert dist_polytopes(c, o, r + 0.5) >= r - 1e-6


@FAST
@given(seed=st.integers(0, 2**32 - 1), m=st.integers(2, 5), n_obs=st.integers(1, 6), r=st.sampled_from([0.1, 0.4]))
def test_errors_match_independent_distances(seed: int, m: int, n_obs: int, r: float) -> None:
    wps, obs, box = random_scene(seed, m, n_obs)
    wp_dist = np.array([[dist_point_polytope(w, o) for o in obs] for w in wps])
    seg_dist = np.array([[dist_segment_polytope(wps[j], wps[j + 1], o, 2 * r + 1) for o in obs] for j in range(m - 1)])
    assume(np.all(np.abs(wp_dist - r) > EDGE) and np.all(np.abs(seg_dist - 2 * r) > EDGE))
    bad_wp = np.flatnonzero(np.any(wp_dist < r, axis=1))
    blocked = np.flatnonzero(np.any(seg_dist < 2 * r, axis=1))
    if bad_wp.size == 0 and blocked.size == 0:
        build_corridors(wps, obs, box, r)
        return
    with pytest.raises(CorridorError) as info:
        build_corridors(wps, obs, box, r)
    err = info.value
    if bad_wp.size:
        assert err.waypoint == bad_wp[0] and err.segment is None
        assert wp_dist[err.waypoint, err.obstacle] < r
        assert f"waypoint {err.waypoint}" in str(err) and f"obstacle {err.obstacle}" in str(err)
    else:
        assert err.segment == blocked[0]
        assert seg_dist[err.segment, err.obstacle] < 2 * r
        assert f"segment {err.segment} (waypoint {err.segment} -> {err.segment + 1})" in str(err)
        assert f"obstacle {err.obstacle} inflated by radius {r:g}" in str(err)


def test_blocked_segment_message() -> None:
    wps = np.array([[0, 0, 0], [5, 0, 0], [5, 5, 0], [10, 5, 0]], dtype=float)
    obs = [polytope_from_box([20, 20, 20], [1, 1, 1]), polytope_from_box([5.5, 2.5, 0.2], [0.4, 1, 1])]
    with pytest.raises(CorridorError) as info:
        build_corridors(wps, obs, None, 0.3)
    assert (info.value.segment, info.value.obstacle, info.value.waypoint) == (1, 1, None)
    assert str(info.value).startswith("segment 1 (waypoint 1 -> 2) is blocked by obstacle 1 inflated by radius 0.3")
    assert isinstance(info.value, ValueError)


def test_waypoint_inside_obstacle_and_outside_map() -> None:
    wps = np.array([[0, 0, 0], [5, 0, 0], [5, 5, 0]], dtype=float)
    obs = [polytope_from_box([5.2, 0.0, 0.0], [0.2, 1, 1])]
    with pytest.raises(CorridorError, match=r"waypoint 1 .* inside obstacle 0 inflated by radius 0.3") as info:
        build_corridors(wps, obs, None, 0.3)
    assert (info.value.waypoint, info.value.obstacle, info.value.segment) == (1, 0, None)
    box = (np.array([-1.0, -1, -1]), np.array([5.2, 6, 1]))
    with pytest.raises(CorridorError, match=r"waypoint 1 .* outside the map box") as info:
        build_corridors(wps, [], box, 0.3)
    assert info.value.waypoint == 1 and info.value.obstacle is None


def test_obstacle_beyond_the_map_boundary_does_not_block() -> None:
    # Ground slab under a low flight: the map floor already keeps it r away.
    wps = np.array([[0, 0, 0.4], [10, 0, 0.4]])
    ground = polytope_from_box([5, 0, -0.5], [30, 30, 1.0])
    box = (np.array([-5.0, -5, 0]), np.array([15.0, 5, 10]))
    (c,) = build_corridors(wps, [ground], box, 0.3)
    assert exclusion_margin(c, polytope_vertices(ground)) >= 0.3 - 1e-12
    with pytest.raises(CorridorError, match="segment 0"):
        build_corridors(wps, [ground], None, 0.3)


@FAST
@given(seed=st.integers(0, 2**32 - 1), r=st.sampled_from([0.0, 0.2, 0.5]))
def test_single_obstacle_plane_is_the_roomiest(seed: int, r: float) -> None:
    """The plane keeps the obstacle exactly r out and leaves the segment gap - r (the most any plane can)."""
    rng = np.random.default_rng(seed)
    p0, p1 = rng.normal(size=3) * 3, rng.normal(size=3) * 3
    obstacle = random_obstacle(rng, (p0 + p1) / 2 + rng.normal(size=3) * 3)
    gap = dist_segment_polytope(p0, p1, obstacle)
    assume(gap >= 2 * r + 1e-3)
    assume(gap < float(np.linalg.norm(p1 - p0)) + 3.0)  # within the default reach: it gets a plane
    (c,) = build_corridors(np.stack([p0, p1]), [obstacle], None, r)
    lo, hi = analysis_boxes(p0[None], p1[None], np.array([np.linalg.norm(p1 - p0) + 3.0]), None, r)
    frame = np.concatenate([hi[0], -lo[0]])
    own = [p for p in range(len(c.b)) if not (np.count_nonzero(c.A[p]) == 1 and np.any(np.isclose(frame, c.b[p])))]
    assert len(own) == 1  # one plane of its own; the others are faces of the analysis box
    c = Polytope(c.A[own], c.b[own])
    assert exclusion_margin(c, polytope_vertices(obstacle)) == pytest.approx(r, abs=1e-9)
    clearance = segment_clearance(p0, p1, c)
    assert clearance >= gap / 2 - r - 1e-9  # at least the mid-margin plane's room
    assert clearance == pytest.approx(gap - r, abs=1e-5)  # max-margin normal: all of the gap


def test_obstacle_behind_another_needs_no_plane() -> None:
    wps = np.array([[0, 0, 0], [10, 0, 0]], dtype=float)
    front = polytope_from_box([5, 3, 0], [20, 1, 20])
    behind = polytope_from_box([5, 6, 0], [2, 1, 2])
    box = (np.array([-10.0, -10, -10]), np.array([20.0, 10, 10]))
    (c,) = build_corridors(wps, [front, behind], box, 0.3)
    check_corridor(c, wps[0], wps[1], [front, behind], 0.3, box)
    assert np.sum(c.A[:, 1] > 0.5) == 1  # one plane towards +y serves both obstacles


@settings(FAST, max_examples=12)
@given(seed=st.integers(0, 2**32 - 1), m=st.integers(2, 6), r=st.sampled_from([0.1, 0.3]), use_map=st.booleans())
def test_update_changes_only_affected_segments(seed: int, m: int, r: float, use_map: bool) -> None:
    wps, old, new, map_box = split_scene(seed, m, r, use_map)
    before = build_corridors(wps, old, map_box, r)
    after, changed = update_corridors(wps, before, old, new, map_box, r)
    new_verts = [verts_of(o) for o in new]
    for j in range(m - 1):
        certified = all(exclusion_margin(before[j], v) >= r - 1e-10 for v in new_verts)
        if j in changed:
            assert not certified and after[j] is not before[j]
        else:
            assert certified and after[j] is before[j]
            assert all(dist_polytopes(before[j], o, r + 0.5) >= r - 1e-6 for o in new)
        check_corridor(after[j], wps[j], wps[j + 1], [*old, *new], r, map_box)


def test_update_reports_blocking_popup() -> None:
    wps = np.array([[0, 0, 0], [5, 0, 0], [5, 5, 0], [10, 5, 0]], dtype=float)
    old = [polytope_from_box([2.5, 3, 0], [1, 1, 1])]
    before = build_corridors(wps, old, None, 0.3)
    with pytest.raises(CorridorError) as info:
        update_corridors(wps, before, old, [polytope_from_box([7.5, 5, 0], [0.5, 0.5, 0.5])], None, 0.3)
    assert (info.value.segment, info.value.obstacle) == (2, 1)
    after, changed = update_corridors(wps, before, old, [], None, 0.3)
    assert changed == [] and all(a is b for a, b in zip(after, before, strict=True))


def test_bad_input_is_named() -> None:
    wps = np.zeros((3, 3))
    wps[1, 0], wps[2, 1] = 1.0, 1.0
    with pytest.raises(ValueError, match="waypoints"):
        build_corridors(wps[:1], [], None, 0.1)
    with pytest.raises(ValueError, match="radius"):
        build_corridors(wps, [], None, -1.0)
    with pytest.raises(ValueError, match=r"obstacles\[1\]: polytope is unbounded"):
        build_corridors(wps, [polytope_from_box([9, 9, 9], [1, 1, 1]), Polytope(np.eye(3), np.ones(3))], None, 0.1)
    with pytest.raises(ValueError, match="map_box"):
        build_corridors(wps, [], (np.zeros(3), np.array([5.0, 5.0, 0.1])), 0.1)
