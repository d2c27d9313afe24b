"""Obstacles given as the corners of an axis-aligned box get their six planes directly (issue 25,
point 2): the same planes as the convex hull, and any other shape still goes to the hull."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from planner_core.formats.io import load_scenario
from planner_core.geometry import axis_box_of, polytope_from_vertices, polytope_vertices
from planner_core.problem import Polytope

BITS = ((np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1).astype(bool)


def corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.where(BITS, hi[None, :], lo[None, :])


def hull_planes(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The reference: qhull's facets (unit normals, n.x <= b), coplanar triangles merged."""
    eq = ConvexHull(points).equations
    A, b = eq[:, :3], -eq[:, 3]
    keep: list[int] = []
    for i in range(A.shape[0]):
        if not any(np.allclose(A[i], A[k], atol=1e-9) and abs(b[i] - b[k]) <= 1e-9 * (1 + abs(b[i])) for k in keep):
            keep.append(i)
    return A[keep], b[keep]


def same_planes(p: Polytope, A: np.ndarray, b: np.ndarray, tol: float) -> bool:
    if p.A.shape[0] != A.shape[0]:
        return False
    for i in range(A.shape[0]):  # every reference plane is one of p's, and the counts agree
        hit = np.all(np.abs(p.A - A[i]) <= 1e-9, axis=1) & (np.abs(p.b - b[i]) <= tol)
        if not hit.any():
            return False
    return True


def random_box(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    scale = 10.0 ** rng.uniform(-2, 3)
    lo = rng.normal(size=3) * scale * rng.uniform(0, 50)
    return lo, lo + rng.uniform(0.01, 5.0, size=3) * scale


@pytest.mark.parametrize("seed", range(40))
def test_box_corners_give_the_hulls_planes(seed: int) -> None:
    rng = np.random.default_rng(seed)
    lo, hi = random_box(rng)
    pts = corners(lo, hi)
    pts = pts[rng.permutation(8)]
    if seed % 3 == 0:  # repeated corners change nothing
        pts = np.concatenate([pts, pts[rng.integers(0, 8, size=3)]])
    assert axis_box_of(pts) is not None
    fast = polytope_from_vertices(pts)
    A, b = hull_planes(pts)
    scale = float(np.max(np.abs(pts)))
    assert same_planes(fast, A, b, 1e-9 * scale)
    assert np.array_equal(np.sort(fast.b), np.sort(np.concatenate([hi, -lo])))  # exact, not just close
    got = polytope_vertices(fast)
    assert {tuple(v) for v in got.tolist()} == {tuple(v) for v in pts.tolist()}


def _not_boxes(rng: np.random.Generator) -> list[tuple[str, np.ndarray]]:
    lo, hi = random_box(rng)
    box = corners(lo, hi)
    c, R = 0.5 * (lo + hi), np.linalg.qr(rng.normal(size=(3, 3)))[0]
    nudged = box.copy()
    nudged[3, 1] = np.nextafter(nudged[3, 1], np.inf)  # one corner off by one rounding step
    prism = np.concatenate([box[:4], box[4:6]])  # 6 corners: a wedge
    return [
        ("rotated", (box - c) @ R.T + c),
        ("nudged", nudged),
        ("missing corner", box[:7]),
        ("interior point", np.concatenate([box, [c]])),
        ("face point", np.concatenate([box, [[c[0], c[1], hi[2]]]])),
        ("wedge", prism),
        ("two boxes' corners", np.concatenate([box, corners(lo, hi + 1.0)])),
    ]


@pytest.mark.parametrize("seed", range(12))
def test_other_shapes_are_not_boxes_and_keep_their_hull(seed: int) -> None:
    for name, pts in _not_boxes(np.random.default_rng(seed)):
        assert axis_box_of(pts) is None, name
        if np.linalg.svd(pts - pts.mean(0), compute_uv=False)[2] < 1e-9 * np.abs(pts).max():
            continue
        poly = polytope_from_vertices(pts)
        A, b = hull_planes(pts)
        assert same_planes(poly, A, b, 1e-7 * float(np.max(np.abs(pts)))), name


def test_flat_box_is_not_a_box() -> None:
    lo, hi = np.zeros(3), np.array([1.0, 2.0, 0.0])
    assert axis_box_of(corners(lo, hi)) is None
    with pytest.raises(ValueError, match="coplanar"):
        polytope_from_vertices(corners(lo, hi))


def test_a_scenario_of_vertex_boxes_builds_the_corridors_of_its_plane_boxes() -> None:
    rng = np.random.default_rng(5)
    wps = [[0.0, 0.0, 1.0], [6.0, 1.0, 1.5], [12.0, -1.0, 1.0], [18.0, 0.0, 2.0]]
    los = [np.array([3.0, 2.5, 0.0]), np.array([9.0, -4.0, 0.0]), np.array([14.0, 2.0, 0.5])]
    his = [lo + rng.uniform(0.5, 2.0, 3) for lo in los]
    base = {"waypoints": wps, "durations": [3.0, 3.0, 3.0], "vehicle_radius": 0.3,
            "bounds": {"velocity": 5, "acceleration": 4}}
    as_planes = load_scenario({**base, "obstacles": [
        {"A": np.concatenate([np.eye(3), -np.eye(3)]).tolist(), "b": np.concatenate([h, -lo]).tolist()}
        for lo, h in zip(los, his, strict=True)]})
    as_corners = load_scenario({**base, "obstacles": [{"vertices": corners(lo, h).tolist()}
                                                      for lo, h in zip(los, his, strict=True)]})
    a, c = as_planes.problem.corridors, as_corners.problem.corridors
    assert a is not None and c is not None
    for pa, pc in zip(a, c, strict=True):
        assert pa is not None and pc is not None
        assert np.array_equal(pa.A, pc.A) and np.array_equal(pa.b, pc.b)


@pytest.mark.parametrize("seed", range(60))
def test_small_hulls_without_qhull_are_qhulls(seed: int) -> None:
    """Up to SMALL_HULL_POINTS points the hull is found by point triples: the same facets and the
    same hull vertices as qhull's, on random clouds (some points inside) at any scale and offset."""
    from planner_core.geometry import SMALL_HULL_POINTS

    rng = np.random.default_rng(1000 + seed)
    k = int(rng.integers(4, SMALL_HULL_POINTS + 1))
    scale = 10.0 ** rng.uniform(-2, 3)
    pts = (rng.normal(size=(k, 3)) + rng.normal(size=3) * 20.0) * scale
    if np.linalg.svd(pts - pts.mean(0), compute_uv=False)[2] < 1e-3 * scale:
        pytest.skip("nearly flat cloud")
    poly = polytope_from_vertices(pts)
    A, b = hull_planes(pts)
    assert same_planes(poly, A, b, 1e-7 * float(np.max(np.abs(pts))))
    assert np.max(pts @ poly.A.T - poly.b) <= 1e-9 * float(np.max(np.abs(pts)))  # every point inside
    hull_v = pts[ConvexHull(pts).vertices]
    got = polytope_vertices(poly)
    gap = np.linalg.norm(got[:, None, :] - hull_v[None, :, :], axis=-1)  # up to normalising's rounding
    tol = 1e-12 * float(np.max(np.abs(pts)))
    assert got.shape == hull_v.shape and np.all(gap.min(axis=0) <= tol) and np.all(gap.min(axis=1) <= tol)


def test_scipy_is_not_imported_for_small_obstacles() -> None:
    import subprocess
    import sys
    from pathlib import Path

    code = ("import sys, numpy as np\nfrom planner_core.geometry import polytope_from_vertices\n"
            "R = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]\n"
            "box = np.array([[x, y, z] for x in (0, 1) for y in (0, 2) for z in (0, 3)], float)\n"
            "polytope_from_vertices(box); polytope_from_vertices(box @ R.T); polytope_from_vertices(box[:6])\n"
            "print('scipy' in sys.modules)")
    root = Path(__file__).resolve().parents[2]
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root, timeout=120,
                         env={"PYTHONPATH": str(root), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_nearly_flat_small_clouds_still_get_a_bounded_hull_holding_every_point() -> None:
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(400):
        pts = rng.normal(size=(int(rng.integers(4, 13)), 3))
        pts[:, 2] *= 10.0 ** rng.uniform(-8.5, -3.0)  # thin slabs, some past the volume check
        try:
            poly = polytope_from_vertices(pts)
        except ValueError as e:
            assert "coplanar" in str(e)
            continue
        assert np.max(pts @ poly.A.T - poly.b) <= 1e-8 * float(np.max(np.abs(pts)))
        assert polytope_vertices(poly).shape[0] >= 4  # bounded and non-empty, else this raises
        checked += 1
    assert checked > 100
