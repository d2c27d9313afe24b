"""A polytope's vertices do not depend on how, or in which process, it was made.

`polytope_vertices` caches its results by the exact bytes of (A, b). A hull built from
vertices once seeded that cache with the vertices it was given, which differ from those
computed from (A, b) in the last bits: a corridor around such an obstacle then came out
differently in the process that read the obstacle than in a planner worker process (a PX4 SIH
flight recorded with the planner in a worker replayed one plan differently in one process:
a plane's normal had z -4e-16 in one, 0 in the other)."""

from __future__ import annotations

import pickle

import numpy as np

from planner_core.geometry import clear_vertex_cache, polytope_vertices
from planner_core.geometry.polytopes import polytope_from_vertices


def test_vertices_are_the_same_wherever_the_polytope_was_made() -> None:
    rng = np.random.default_rng(3)
    for k in range(60):
        # rotated boxes, prisms and random clouds (a handful of points, and more: qhull)
        n = (6, 8, 10, 30)[k % 4]
        pts = rng.normal(size=(n, 3)) * rng.uniform(0.2, 3.0, 3) + rng.uniform(-20, 20, 3)
        poly = polytope_from_vertices(pts)
        here = polytope_vertices(poly)
        clear_vertex_cache()
        elsewhere = polytope_vertices(pickle.loads(pickle.dumps(poly)))  # a worker's copy
        assert np.array_equal(here, elsewhere), k  # failed for most clouds when the hull seeded the cache


def test_a_box_from_its_corners_is_exact_either_way() -> None:
    lo, hi = np.array([1.0, -2.0, -3.0]), np.array([2.5, 0.5, -1.0])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    poly = polytope_from_vertices(corners)
    here = polytope_vertices(poly)
    clear_vertex_cache()
    assert np.array_equal(here, polytope_vertices(pickle.loads(pickle.dumps(poly))))
    assert {tuple(v) for v in here} == {tuple(v) for v in corners}
