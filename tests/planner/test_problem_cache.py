"""ProblemCache builds per segment what the numpy paths touch, and keeps a bounded number of blocks."""

from __future__ import annotations

import numpy as np
import pytest

from planner_core import Bounds, Polytope, Problem, jets_cache
from planner_core.constraints import hull_maps
from planner_core.jets import ProblemCache


def _problem(seed: int, m: int) -> Problem:
    """Random walk, uneven durations, a box corridor around each leg (none on every fifth)."""
    rng = np.random.default_rng(seed)
    wps = np.cumsum(rng.normal(size=(m, 3)) * 3.0, axis=0)
    eye = np.eye(3)
    cors = [None if i % 5 == 3 else Polytope(np.concatenate([eye, -eye]), np.concatenate(
        [np.maximum(wps[i], wps[i + 1]) + 1.0, -(np.minimum(wps[i], wps[i + 1]) - 1.0)])) for i in range(m - 1)]
    durations = rng.uniform(1.0, 4.0, size=m - 1)
    return Problem.from_waypoints(wps, durations, Bounds.symmetric(7, 6.5, 15, 60), tuple(cors))


def test_per_segment_maps_equal_the_whole_problems() -> None:
    problem = _problem(2, 40)
    cache = ProblemCache(problem)
    segs = np.array([0, 7, 8, 21, 38], dtype=np.int64)
    part = cache.hull_of(segs)
    one = cache.hull_of(21)
    costs = cache.cost30(4, segs.tolist())
    assert "hull" not in cache.__dict__ and 4 not in cache._cost  # neither was built for all segments
    whole = hull_maps(problem.durations)
    np.testing.assert_allclose(part, whole[segs], rtol=1e-15, atol=0.0)
    np.testing.assert_allclose(one, whole[21], rtol=1e-15, atol=0.0)
    np.testing.assert_allclose(costs, cache.cost30(4)[segs], rtol=1e-15, atol=0.0)
    np.testing.assert_array_equal(cache.hull_of(segs), cache.hull[segs])  # once built, read from it


def test_row_blocks_kept_are_bounded_and_rebuilt_the_same(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(jets_cache, "BLOCKS_KEPT", 5)
    problem = _problem(2, 40)
    cache = ProblemCache(problem)
    first = cache.blocks(3)
    for s in range(10, 30):
        cache.blocks(s)
        cache.blocks(3)  # used all along: never the least recently used
        assert len(cache._blocks) <= 5
    assert cache.blocks(3) is first
    early = cache.blocks(10)  # evicted long ago: built again, the same rows
    ref = ProblemCache(problem).blocks(10)
    for name in ("A", "B", "c0", "lim"):
        np.testing.assert_array_equal(getattr(early, name), getattr(ref, name))
