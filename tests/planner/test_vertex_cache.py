"""A polytope's vertices do not depend on how, or in which process, it was made.

`polytope_vertices` caches its results by the exact bytes of (A, b). A hull built from vertices
seeds that cache with its own vertices (cheaper than enumerating, and the only way for a nearly
flat hull), which differ from an enumeration from (A, b) in the last bits. Before, a planner
process that received the obstacle enumerated them, so a corridor around it came out differently
there than in the process that read it: a PX4 SIH flight recorded with the planner in a worker
process replayed one plan differently in one process (a plane's normal had z -4e-16 in one, 0 in
the other). The hull's vertices now travel with the polytope."""

from __future__ import annotations

import multiprocessing
import pickle
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from planner_core import build_corridors
from planner_core.geometry import clear_vertex_cache, polytope_vertices
from planner_core.geometry.polytopes import enumerate_vertices, normalised, polytope_from_vertices


def _clouds(n: int) -> list[np.ndarray]:
    rng = np.random.default_rng(3)
    return [rng.normal(size=((6, 8, 10, 30)[k % 4], 3)) * rng.uniform(0.2, 3.0, 3) + rng.uniform(-20, 20, 3)
            for k in range(n)]


def test_vertices_are_the_same_wherever_the_polytope_was_made() -> None:
    differ = 0
    for k, pts in enumerate(_clouds(60)):
        poly = polytope_from_vertices(pts)
        here = polytope_vertices(poly)
        clear_vertex_cache()
        elsewhere = polytope_vertices(pickle.loads(pickle.dumps(poly)))  # a planner process's copy
        assert np.array_equal(here, elsewhere), k
        A, b = normalised(poly, "p")
        enumerated = enumerate_vertices(A, b)
        differ += enumerated.shape != here.shape or not np.array_equal(np.sort(enumerated, 0), np.sort(here, 0))
    assert differ > 0  # the premise: an enumeration from (A, b) is not the hull's own vertices


def test_corridors_around_a_hull_are_the_same_in_a_planner_process() -> None:
    """The deployed shape: the obstacle read in the service, the corridors built in a spawned
    planner process: bit for bit those built where it was read."""
    wps = np.array([[-25.0, -25.0, -25.0], [0.0, 0.0, 0.0], [25.0, 25.0, 25.0]])
    obstacles = [polytope_from_vertices(pts) for pts in _clouds(8)]
    box = (np.full(3, -60.0), np.full(3, 60.0))
    here = build_corridors(wps, obstacles, box, 0.3)
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        there = pool.submit(build_corridors, wps, obstacles, box, 0.3).result()
    assert len(here) == len(there)
    for a, b in zip(here, there, strict=True):
        assert np.array_equal(a.A, b.A) and np.array_equal(a.b, b.b)


def test_a_box_from_its_corners_is_exact_either_way() -> None:
    lo, hi = np.array([1.0, -2.0, -3.0]), np.array([2.5, 0.5, -1.0])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    poly = polytope_from_vertices(corners)
    here = polytope_vertices(poly)
    clear_vertex_cache()
    assert np.array_equal(here, polytope_vertices(pickle.loads(pickle.dumps(poly))))
    assert {tuple(v) for v in here} == {tuple(v) for v in corners}
