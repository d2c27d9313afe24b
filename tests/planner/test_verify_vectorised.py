"""verify() (vectorised over segments, blocked, reductions first) against a plain per-segment
reference on random trajectories, and injected violations found at the right place."""

from __future__ import annotations

from dataclasses import replace
from math import comb, factorial

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from planner_core import Bounds, Polytope, Problem, Trajectory, verify
from planner_core.bezier import split_segment
from planner_core.constraints import HULL_PIECES
from planner_core.verify import SAMPLES_PER_SEGMENT, VerifyReport, Worst

N = 9
FAST = settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# --- reference: one segment, one order at a time, written from the definitions ---------


def _hodograph(ctrl: np.ndarray, k: int, duration: float) -> np.ndarray:
    pts = ctrl
    for _ in range(k):
        pts = np.diff(pts, axis=0)
    return pts * (factorial(N) / factorial(N - k)) / duration**k


def _bernstein(n: int, u: np.ndarray) -> np.ndarray:
    i = np.arange(n + 1)
    return np.array([comb(n, j) for j in range(n + 1)]) * u[:, None] ** i * (1 - u[:, None]) ** (n - i)


def _pieces(pts: np.ndarray, pieces: int) -> np.ndarray:
    """Control points of the curve's restrictions to [i/p, (i+1)/p], one piece after the other,
    by repeated de Casteljau splits (verify uses the stacked linear map)."""
    out = []
    rest = pts
    for i in range(pieces - 1):
        left, rest = split_segment(rest, 1.0 / (pieces - i))
        out.append(left)
    out.append(rest)
    return np.concatenate(out)


def reference_bounds(traj: Trajectory, problem: Problem) -> tuple[Worst, Worst]:
    """Order by order, segment by segment; the first worst entry wins (order, segment, index, axis).
    The hull is that of the hodographs' HULL_PIECES pieces (the planner's certificate)."""
    u = np.linspace(0.0, 1.0, SAMPLES_PER_SEGMENT)
    hull, samp = Worst(-np.inf), Worst(-np.inf)
    lo, hi = problem.bounds.lo, problem.bounds.hi
    for k in range(1, 5):
        basis = _bernstein(N - k, u)
        for s in range(traj.n_segments):
            d = traj.times[s + 1] - traj.times[s]
            pts = _hodograph(traj.control_points[s], k, d)
            cert = _pieces(pts, HULL_PIECES)
            v = np.maximum(cert - hi[k - 1], lo[k - 1] - cert)
            i, a = np.unravel_index(int(np.argmax(v)), v.shape)
            if v[i, a] > hull.value:
                hull = Worst(float(v[i, a]), s, k, int(a))
            vals = basis @ pts
            v = np.maximum(vals - hi[k - 1], lo[k - 1] - vals)
            t, a = np.unravel_index(int(np.argmax(v)), v.shape)
            if v[t, a] > samp.value:
                samp = Worst(float(v[t, a]), s, k, int(a), float(traj.times[s] + u[t] * d))
    return hull, samp


def reference_corridors(traj: Trajectory, problem: Problem) -> tuple[Worst, Worst]:
    u = np.linspace(0.0, 1.0, SAMPLES_PER_SEGMENT)
    hull, samp = Worst(-np.inf), Worst(-np.inf)
    assert problem.corridors is not None
    for s, poly in enumerate(problem.corridors):
        if poly is None or poly.A.shape[0] == 0:
            continue
        ctrl = traj.control_points[s]
        for p in ctrl:
            v = float(np.max(poly.A @ p - poly.b))
            if v > hull.value:
                hull = Worst(v, s)
        pts = _bernstein(N, u) @ ctrl
        for t, p in enumerate(pts):
            v = float(np.max(poly.A @ p - poly.b))
            if v > samp.value:
                samp = Worst(v, s, time=float(traj.times[s] + u[t] * (traj.times[s + 1] - traj.times[s])))
    return hull, samp


# --- random trajectories --------------------------------------------------------------


def random_case(seed: int, s: int, none_every: int = 0) -> tuple[Trajectory, Problem]:
    """Random control points (not a plan: nothing is smooth) with random bounds and corridors
    of varying plane counts, some None or empty."""
    rng = np.random.default_rng(seed)
    ctrl = np.cumsum(rng.normal(size=(s, N + 1, 3)), axis=1) + 5.0 * np.arange(s)[:, None, None]
    times = np.concatenate([[rng.uniform(-5, 5)], rng.uniform(0.5, 3.0, s)]).cumsum()
    wps = np.concatenate([ctrl[:, 0], ctrl[-1:, -1]])
    hi = rng.uniform(5.0, 400.0, size=(4, 3))
    lo = -rng.uniform(5.0, 400.0, size=(4, 3))
    cors: list[Polytope | None] = []
    for j in range(s):
        if none_every and j % none_every == 0:
            cors.append(None if j % (2 * none_every) == 0 else Polytope(np.zeros((0, 3)), np.zeros(0)))
            continue
        k = int(rng.integers(1, 12))
        A = rng.normal(size=(k, 3))
        A /= np.linalg.norm(A, axis=1, keepdims=True)
        b = np.max(ctrl[j] @ A.T, axis=0) + rng.normal(scale=0.5, size=k)
        cors.append(Polytope(A, b))
    problem = Problem(wps, times, Bounds(lo, hi), np.zeros((5, 3)), np.zeros((5, 3)), tuple(cors))
    return Trajectory(times, ctrl), problem


def _same(w: Worst, ref: Worst, rel: float = 1e-9) -> None:
    assert w.value == pytest.approx(ref.value, rel=rel, abs=1e-9)
    assert (w.segment, w.order, w.axis) == (ref.segment, ref.order, ref.axis)
    if ref.time is None:
        assert w.time is None
    else:
        assert w.time == pytest.approx(ref.time, rel=1e-12, abs=1e-12)


@FAST
@given(seed=st.integers(0, 2**32 - 1), s=st.integers(1, 300), none_every=st.sampled_from([0, 3, 7]))
def test_matches_per_segment_reference(seed: int, s: int, none_every: int) -> None:
    traj, problem = random_case(seed, s, none_every)
    rep = verify(traj, problem)
    bh, bs = reference_bounds(traj, problem)
    _same(rep.bound_violation_hull, bh)
    _same(rep.bound_violation_sampled, bs)
    ch, cs = reference_corridors(traj, problem)
    _same(rep.corridor_violation_hull, ch)
    _same(rep.corridor_violation_sampled, cs)
    assert isinstance(rep, VerifyReport) and not rep.ok  # random points: not a flyable plan


def _smooth_case(s: int, seed: int = 0) -> tuple[Trajectory, Problem]:
    """A C^4 trajectory: one degree-9 polynomial split into s segments (so it verifies)."""
    rng = np.random.default_rng(seed)
    whole = np.cumsum(rng.normal(size=(N + 1, 3)), axis=0) * 10.0
    pieces = []
    rest = whole
    for j in range(s - 1):
        left, rest = split_segment(rest, 1.0 / (s - j))
        pieces.append(left)
    pieces.append(rest)
    ctrl = np.stack(pieces)
    times = np.linspace(0.0, 2.0 * s, s + 1)
    wps = np.concatenate([ctrl[:, 0], ctrl[-1:, -1]])
    traj = Trajectory(times, ctrl)
    problem = Problem(wps, times, Bounds.unbounded(), traj.jet(times[0]), traj.jet(times[-1]))
    return traj, problem


@pytest.mark.parametrize(("s", "target"), [(2, 1), (300, 0), (300, 127), (300, 128), (300, 299)])
@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_injected_bound_violation_is_found_at_its_segment_and_order(s: int, target: int, k: int) -> None:
    """Targets on both sides of verify's block boundaries (blocks of 128 segments)."""
    traj, problem = _smooth_case(s)
    assert verify(traj, problem).ok
    # bounds just inside every segment's hodograph of order k, except a spike in `target`
    d = traj.times[1] - traj.times[0]
    peaks = np.array([np.abs(_pieces(_hodograph(c, k, d), HULL_PIECES)).max(axis=0) for c in traj.control_points])
    hi = np.full((4, 3), np.inf)
    hi[k - 1] = peaks.max(axis=0) * 1.01
    bounds = Bounds(-hi, hi)
    ctrl = traj.control_points.copy()
    ctrl[target, 4 + (k % 2)] += 50.0 * hi[k - 1] * d**k  # moves orders >= 1 of that segment only
    bad = replace(traj, control_points=ctrl)
    rep = verify(bad, replace(problem, bounds=bounds))
    hull, samp = reference_bounds(bad, replace(problem, bounds=bounds))
    assert not rep.ok
    _same(rep.bound_violation_hull, hull)
    _same(rep.bound_violation_sampled, samp)
    assert rep.bound_violation_hull.segment == target
    assert rep.bound_violation_sampled.segment == target
    assert rep.bound_violation_hull.order == k and rep.bound_violation_sampled.order == k


@pytest.mark.parametrize(("s", "target"), [(3, 1), (260, 39), (260, 258)])
def test_injected_corridor_violation_is_found_in_a_late_block(s: int, target: int) -> None:
    """Corridor 39's 7 planes straddle verify's first block of 240 plane rows."""
    traj, problem = _smooth_case(s, seed=2)
    # one loose box per segment, then a plane through the middle of one late segment's curve
    lo = traj.control_points.min(axis=1) - 1.0
    hi = traj.control_points.max(axis=1) + 1.0
    eye = np.eye(3)
    cors = [Polytope(np.vstack([eye, -eye]), np.concatenate([h, -lo_])) for lo_, h in zip(lo, hi, strict=True)]
    mid = traj.evaluate(0.5 * (traj.times[target] + traj.times[target + 1]))
    normal = np.array([1.0, 0.0, 0.0])
    cors[target] = Polytope(np.vstack([cors[target].A, normal]), np.append(cors[target].b, mid @ normal - 0.01))
    problem = replace(problem, corridors=tuple(cors))
    rep = verify(traj, problem)
    ch, cs = reference_corridors(traj, problem)
    assert not rep.ok
    _same(rep.corridor_violation_hull, ch)
    _same(rep.corridor_violation_sampled, cs)
    assert rep.corridor_violation_sampled.segment == target
    assert rep.corridor_violation_sampled.value >= 0.01 - 1e-9


def test_unbounded_and_no_corridors_report_nothing() -> None:
    traj, problem = _smooth_case(5)
    rep = verify(traj, problem)
    assert rep.ok
    assert rep.bound_violation_hull.value == -np.inf and rep.bound_violation_sampled.value == -np.inf
    assert rep.corridor_violation_hull == Worst(-np.inf)
    empty = replace(problem, corridors=(None, Polytope(np.zeros((0, 3)), np.zeros(0)), None, None, None))
    assert verify(traj, empty).corridor_violation_sampled == Worst(-np.inf)


def test_continuity_violation_found_at_its_junction() -> None:
    traj, problem = _smooth_case(200, seed=3)
    ctrl = traj.control_points.copy()
    ctrl[150, 3] += [0.0, 0.0, 1e-2]  # jerk (and snap) jump at waypoint 150
    rep = verify(replace(traj, control_points=ctrl), problem)
    assert not rep.ok
    assert rep.continuity_error.segment == 150 and rep.continuity_error.order in (3, 4)
    assert rep.continuity_error.axis == 2
