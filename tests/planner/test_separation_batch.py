"""One trajectory against many at once (planner_core.separation_batch and the batched certificate):
the stacked pair-by-pair answers must be the very ones computed pair by pair, the cheaper boxes and
planes must still bound what they claim to, and a batch must refuse exactly what pairs refuse."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from planner_core.problem import Trajectory
from planner_core.separation import certify_many, common_pieces, verify_separation
from planner_core.separation_batch import batch_knots, locate_packed, pack, span_boxes
from planner_core.separation_pieces import (
    CONVERGED,
    KNOT_TOL,
    best_plane,
    common_knots,
    halves_matrix,
    locate,
    max_margin_plane,
    nearest_planes,
    pieces_between,
)
from tests.planner.test_separation import random_trajectory


def _others(rng: np.random.Generator, a: Trajectory, n: int) -> list[Trajectory]:
    out = [random_trajectory(rng, float(rng.uniform(-3.0, 6.0)), int(rng.integers(1, 6))) for _ in range(n)]
    # knots that nearly meet ours (within KNOT_TOL and just beyond it): the merge must match
    b = out[0]
    shifted = b.times - b.times[1] + a.times[1] + 0.5 * KNOT_TOL
    out[0] = Trajectory(shifted, b.control_points)
    shifted = b.times - b.times[1] + a.times[-1] + 3.0 * KNOT_TOL
    out[1] = Trajectory(shifted, b.control_points)
    return out


def test_batch_knots_and_locations_are_those_of_each_pair() -> None:
    rng = np.random.default_rng(3)
    for trial in range(30):
        a = random_trajectory(rng, 0.0, int(rng.integers(1, 5)))
        others = _others(rng, a, 12)
        p = pack(others)
        owners = rng.permutation(len(others))[: rng.integers(1, len(others) + 1)]
        span = None if trial % 3 == 0 else (float(rng.uniform(-1.0, 3.0)), float(rng.uniform(3.0, 9.0)))
        extra = None if trial % 2 else np.sort(rng.uniform(-1.0, 8.0, 4))
        pair, t0, t1, counts = batch_knots(a, p, owners, span, extra)
        assert counts.sum() == pair.size
        for j, k in enumerate(owners.tolist()):
            ref = common_knots(a, others[k], extra, span)
            got = np.append(t0[pair == j], t1[pair == j][-1:])
            if ref.size < 2:
                assert counts[j] == 0
                continue
            np.testing.assert_array_equal(got, ref)
            seg, v0, v1, h = locate(others[k], ref[:-1], ref[1:])
            for how in (p, replace(p, padded=None)):  # a count over padded knots, or a binary search
                row, u0, u1, held = locate_packed(how, np.full(ref.size - 1, k), ref[:-1], ref[1:])
                np.testing.assert_array_equal(row - p.rows[k], seg)
                np.testing.assert_array_equal(u0, v0)
                np.testing.assert_array_equal(u1, v1)
                np.testing.assert_array_equal(held, h)


def test_span_boxes_hold_every_piece_and_are_no_looser_than_the_segment() -> None:
    rng = np.random.default_rng(4)
    for _ in range(20):
        a = random_trajectory(rng, 0.0, int(rng.integers(1, 5)))
        t0 = np.sort(rng.uniform(a.t0, a.t_end + 2.0, 300))
        t1 = t0 + rng.uniform(0.0, 0.6, t0.size)
        # keep each interval inside one segment (or after the end), as the callers do
        seg = np.searchsorted(a.times, t0, side="right") - 1
        end = np.where(seg < a.n_segments, a.times[np.minimum(seg + 1, a.n_segments)], np.inf)
        t1 = np.minimum(t1, end)
        s, u0, u1, held = locate(a, t0, t1)
        lo, hi = span_boxes(a, s, u0, u1, held)
        pts = pieces_between(a, t0, t1)
        assert (pts >= lo[:, None] - 1e-9).all() and (pts <= hi[:, None] + 1e-9).all()
        whole = a.control_points[s]
        inside = t0 < a.t_end - KNOT_TOL
        assert (lo[inside] >= whole[inside].min(axis=1) - 1e-9).all()
        assert (hi[inside] <= whole[inside].max(axis=1) + 1e-9).all()


def test_gilbert_planes_are_real_gaps_and_bounds_hold() -> None:
    rng = np.random.default_rng(5)
    k = 200
    pa = rng.normal(size=(k, 10, 3))
    pb = rng.normal(size=(k, 10, 3)) + rng.normal(size=(k, 1, 3)) * rng.uniform(0.0, 6.0, (k, 1, 1))
    need = rng.uniform(0.0, 3.0, k)
    n, gap, c, bound = nearest_planes(pa, pb, need)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    # the gap is what the points give along n, never the solver's word
    real = np.einsum("kx,kpx->kp", n, pb).min(axis=1) - np.einsum("kx,kpx->kp", n, pa).max(axis=1)
    ok = np.isfinite(gap)
    np.testing.assert_allclose(gap[ok], real[ok], atol=1e-12)
    mid = 0.5 * (np.einsum("kx,kpx->kp", n, pb).min(axis=1) + np.einsum("kx,kpx->kp", n, pa).max(axis=1))
    np.testing.assert_allclose(c[ok], mid[ok], atol=1e-12)
    for i in range(k):
        mm = max_margin_plane(pa[i], pb[i])
        if mm is None:
            continue
        assert gap[i] <= mm[1] + 1e-9  # no plane beats the max-margin one
        assert bound[i] >= mm[1] - 1e-6  # |x| bounds the hulls' distance
        if bound[i] < need[i]:
            assert mm[1] < need[i] + 1e-6  # "no plane can clear it" is true
    # run to convergence, the plane is the max-margin one (the faces' direction)
    n, gap, _c, bound = nearest_planes(pa, pb, None, steps=200)
    converged = bound - gap <= CONVERGED * np.maximum(bound, 1.0)
    # (where they do not, in a face-to-face case, the caller asks the QP)
    checked = 0
    for i in np.flatnonzero(converged).tolist():
        mm = max_margin_plane(pa[i], pb[i])
        if mm is None:
            continue
        checked += 1
        assert abs(gap[i] - mm[1]) <= 1e-6 * max(1.0, mm[1])
        assert float(n[i] @ mm[0]) > 1.0 - 1e-6
    assert checked > 20


def _first_refusal(a: Trajectory, b: Trajectory, need: float, depth: int = 4) -> int | None:
    """The interval certifying pair by pair with the best plane (cheap or max-margin) on every
    piece, halving up to `depth` times, refuses first (the method before batching); None: none."""
    knots, pa, pb = common_pieces(a, b)
    halves = halves_matrix()
    for i in range(knots.size - 1):
        stack = [(pa[i], pb[i], 0)]
        while stack:
            qa, qb, d = stack.pop()
            if best_plane(qa, qb, need)[1] >= need:
                continue
            if d >= depth:
                return i
            stack += [(halves[1] @ qa, halves[1] @ qb, d + 1), (halves[0] @ qa, halves[0] @ qb, d + 1)]
    return None


def test_a_batch_certifies_and_refuses_exactly_as_pairs_do() -> None:
    rng = np.random.default_rng(6)
    seen = set()
    for s in (0.5, 2.0, 6.0):
        a = random_trajectory(rng, 0.0, 3)
        others = [random_trajectory(rng, float(rng.uniform(-2.0, 4.0)), 3) for _ in range(25)]
        batch = certify_many(a, others, s)
        for b, chk in zip(others, batch, strict=True):
            assert chk.interval == _first_refusal(a, b, s)
            seen.add(chk.ok)
            if chk.certificate is not None:
                assert verify_separation(a, b, chk.certificate).ok
            else:
                assert not chk.ok and chk.shortfall > 0.0
    assert seen == {True, False}
