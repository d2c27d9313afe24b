"""update_corridors(prune=False), the in-flight path: same region and certificates as the
pruned update."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from planner_core.geometry import (
    build_corridors,
    exclusion_margin,
    polytope_vertices,
    update_corridors,
)
from tests.planner.test_corridors import FAST, split_scene


@settings(FAST, max_examples=12)
@given(seed=st.integers(0, 2**32 - 1), m=st.integers(2, 6), r=st.sampled_from([0.1, 0.3]), use_map=st.booleans())
def test_unpruned_update_keeps_region_and_certificates(seed: int, m: int, r: float, use_map: bool) -> None:
    wps, old, new, map_box = split_scene(seed, m, r, use_map)
    before = build_corridors(wps, old, map_box, r)
    pruned, changed = update_corridors(wps, before, old, new, map_box, r)
    fast, changed_fast = update_corridors(wps, before, old, new, map_box, r, prune=False)
    assert changed_fast == changed
    rng = np.random.default_rng(seed)
    lo, hi = np.min(wps, axis=0) - 6.0, np.max(wps, axis=0) + 6.0
    pts = rng.uniform(lo, hi, size=(4000, 3))
    for j in range(m - 1):
        if j not in changed:
            assert fast[j] is before[j]
            continue
        # the same region as the pruned update (up to rounding at the boundary)
        inside_fast = np.all(pts @ fast[j].A.T <= fast[j].b + 1e-9, axis=1)
        inside_pruned = np.all(pts @ pruned[j].A.T <= pruned[j].b + 1e-9, axis=1)
        assert np.array_equal(inside_fast, inside_pruned)
        # only ever cut further: never a point the old corridor excluded
        inside_before = np.all(pts @ before[j].A.T <= before[j].b + 1e-9, axis=1)
        assert not np.any(inside_fast & ~inside_before)
        # the straight segment still fits, and every obstacle has a single-plane certificate
        assert float(np.max(wps[j : j + 2] @ fast[j].A.T - fast[j].b)) <= 1e-9
        for o in [*old, *new]:
            assert exclusion_margin(fast[j], polytope_vertices(o)) >= r - 1e-9
