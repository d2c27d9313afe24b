"""Bézier primitives against closed forms, finite differences and exact subdivision."""

from __future__ import annotations

from math import comb

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planner_core.bezier import (
    bernstein_basis,
    end_jet,
    end_map,
    evaluate_segment,
    hodograph,
    segment_at,
    segment_from_jets,
    segments_at,
    segments_from_jets,
    split_segment,
    start_jet,
    start_map,
)
from planner_core.constraints import bernstein_gram, integrated_cost

seeds = st.integers(0, 2**31 - 1)
durations = st.floats(0.3, 6.0)


def _ctrl(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(scale=3.0, size=(10, 3))


def test_basis_partition_of_unity_and_closed_form() -> None:
    u = np.linspace(0, 1, 11)
    B = bernstein_basis(9, u)
    assert np.allclose(B.sum(axis=1), 1.0)
    i = 4
    assert np.allclose(B[:, i], comb(9, i) * u**i * (1 - u) ** (9 - i))


def test_power_basis_closed_form() -> None:
    # x(t) = t^9 on [0, Δ] has control points (Δ^9) δ_{i9}; its derivatives are known
    d = 1.7
    ctrl = np.zeros((10, 3))
    ctrl[9] = d**9
    u = np.array([0.3, 0.8])
    t = u * d
    for k in range(5):
        expect = np.prod(np.arange(9, 9 - k, -1)) * t ** (9 - k)
        assert np.allclose(evaluate_segment(ctrl, d, u, k)[:, 0], expect, rtol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seeds, durations)
def test_hodograph_matches_finite_differences(seed: int, d: float) -> None:
    ctrl = _ctrl(seed)
    u = np.linspace(0.1, 0.9, 5)
    h = 1e-5
    for k in range(1, 5):
        lo = evaluate_segment(ctrl, d, u - h / d, k - 1)
        hi = evaluate_segment(ctrl, d, u + h / d, k - 1)
        fd = (hi - lo) / (2 * h)
        exact = evaluate_segment(ctrl, d, u, k)
        assert np.allclose(fd, exact, rtol=1e-5, atol=1e-5 * (1 + np.abs(exact).max()))


@settings(max_examples=25, deadline=None)
@given(seeds, durations, st.floats(0.05, 0.95))
def test_split_is_exact(seed: int, d: float, s: float) -> None:
    ctrl = _ctrl(seed)
    left, right = split_segment(ctrl, s)
    u = np.linspace(0, 1, 13)
    for k in range(5):
        whole_l = evaluate_segment(ctrl, d, u * s, k)
        whole_r = evaluate_segment(ctrl, d, s + u * (1 - s), k)
        # relative to the derivative's size: short pieces have large high derivatives
        scale = 1e-9 * (1.0 + max(np.abs(whole_l).max(), np.abs(whole_r).max()))
        assert np.allclose(evaluate_segment(left, d * s, u, k), whole_l, rtol=0, atol=scale)
        assert np.allclose(evaluate_segment(right, d * (1 - s), u, k), whole_r, rtol=0, atol=scale)


@settings(max_examples=25, deadline=None)
@given(seeds, durations)
def test_jet_maps_round_trip(seed: int, d: float) -> None:
    rng = np.random.default_rng(seed)
    j0, j1 = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    ctrl = segment_from_jets(j0, j1, d)
    assert np.allclose(start_jet(ctrl, d), j0, atol=1e-9)
    assert np.allclose(end_jet(ctrl, d), j1, atol=1e-9)
    # and the other way: control points -> jets -> control points
    c = _ctrl(seed)
    back = np.concatenate([start_map(d) @ start_jet(c, d), end_map(d) @ end_jet(c, d)])
    assert np.allclose(back, c, atol=1e-9)


def test_segments_from_jets_matches_single() -> None:
    rng = np.random.default_rng(1)
    jets = rng.normal(size=(5, 5, 3))
    d = np.array([1.0, 2.5, 0.7, 3.1])
    many = segments_from_jets(jets, d)
    for s in range(4):
        assert np.allclose(many[s], segment_from_jets(jets[s], jets[s + 1], d[s]))


def test_hodograph_closed_form() -> None:
    ctrl = _ctrl(3)
    d = 2.0
    expect = 9 / d * (ctrl[1:] - ctrl[:-1])
    assert np.allclose(hodograph(ctrl, 1, d), expect)


@pytest.mark.parametrize("order", [3, 4])
def test_integrated_cost_matches_quadrature(order: int) -> None:
    ctrl = _ctrl(5)[None]
    d = np.array([1.3])
    u = np.linspace(0, 1, 20001)
    vals = evaluate_segment(ctrl[0], d[0], u, order)
    quad = np.trapezoid((vals**2).sum(axis=1), u) * d[0]
    assert integrated_cost(ctrl, d, order) == pytest.approx(quad, rel=1e-6)


def test_bernstein_gram_closed_form() -> None:
    g = bernstein_gram(5)
    u = np.linspace(0, 1, 200001)
    B = bernstein_basis(5, u)
    quad = np.trapezoid(B[:, :, None] * B[:, None, :], u, axis=0)
    assert np.allclose(g, quad, atol=1e-9)


@given(st.lists(st.floats(0.01, 5.0), min_size=1, max_size=8), st.floats(-100.0, 100.0),
       st.lists(st.floats(-3.0, 40.0), max_size=20))
def test_the_segment_of_a_time_is_the_one_that_holds_it(durations: list[float], t0: float, ts: list[float]) -> None:
    """One reading of "which segment is t in" for every caller (samplers, swaps, corridors):
    the later segment at a knot, the first before the span, the last at and after its end."""
    times = t0 + np.concatenate([[0.0], np.cumsum(durations)])
    last = len(durations) - 1
    probes = [t0 + t for t in ts] + list(times)  # every knot too
    for t in probes:
        s = segment_at(times, t)
        if t < times[-1]:
            assert times[s] <= t < times[s + 1] or (s == 0 and t < times[0])
        else:
            assert s == last
    assert segments_at(times, np.array(probes)).tolist() == [segment_at(times, t) for t in probes]
