"""Bernstein/Bézier primitives of degree 9, vectorised over times and segments.

Everything the planner states as a constraint is a linear map of control
points, and control points are a linear map of the two end jets (method.md,
"the key reparametrisation"). The matrices here are those maps.
"""

from __future__ import annotations

from functools import cache, lru_cache
from math import comb, factorial
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from planner_core.problem import Trajectory  # the value type sits above this module

FloatArray = NDArray[np.float64]

DEGREE = 9
JET_ORDER = 5  # position .. snap

N = DEGREE


@cache
def _difference_matrix(k: int, n: int = N) -> FloatArray:
    """(n-k+1, n+1) matrix of the k-th forward difference Δ^k P^i."""
    out = np.zeros((n - k + 1, n + 1))
    for i in range(n - k + 1):
        for q in range(k + 1):
            out[i, i + q] = (-1) ** (k - q) * comb(k, q)
    out.setflags(write=False)
    return out


def falling(n: int, k: int) -> float:
    """n! / (n-k)!"""
    return float(factorial(n) // factorial(n - k))


def hodograph_matrix(k: int, duration: float, n: int = N) -> FloatArray:
    """(n-k+1, n+1) map from control points to the order-k hodograph's control points."""
    return _difference_matrix(k, n) * (falling(n, k) / duration**k)


def hodograph(ctrl: FloatArray, k: int, duration: float) -> FloatArray:
    """Control points of the k-th time derivative of one segment, shape (10-k, 3)."""
    n = ctrl.shape[-2] - 1
    return hodograph_matrix(k, duration, n) @ ctrl


def hodographs(ctrl: FloatArray, k: int, durations: FloatArray) -> FloatArray:
    """Order-k hodograph control points of many segments: (s, 10, 3) -> (s, 10-k, 3)."""
    n = ctrl.shape[-2] - 1
    scale = falling(n, k) / np.asarray(durations, dtype=float) ** k
    out: FloatArray = np.matmul(_difference_matrix(k, n), ctrl) * scale[:, None, None]
    return out


def bernstein_basis(n: int, u: FloatArray) -> FloatArray:
    """Bernstein basis of degree n at parameters u: shape (len(u), n+1)."""
    u = np.atleast_1d(np.asarray(u, dtype=float))[:, None]
    i = np.arange(n + 1)[None, :]
    coeffs = np.array([comb(n, j) for j in range(n + 1)], dtype=float)[None, :]
    return np.asarray(coeffs * u**i * (1.0 - u) ** (n - i))


def evaluate_segment(ctrl: FloatArray, duration: float, u: FloatArray, order: int = 0) -> FloatArray:
    """Derivative `order` of one segment at parameters u in [0, 1]: shape (len(u), 3)."""
    n = ctrl.shape[0] - 1
    if order > n:
        return np.zeros((np.atleast_1d(u).shape[0], ctrl.shape[1]))
    pts = ctrl if order == 0 else hodograph(ctrl, order, duration)
    return bernstein_basis(n - order, u) @ pts


# --- jet <-> control points -------------------------------------------------


@lru_cache(maxsize=4096)
def _start_map_cached(duration: float) -> FloatArray:
    m = np.zeros((JET_ORDER, JET_ORDER))
    for k in range(JET_ORDER):
        for q in range(k + 1):
            m[k, q] = comb(k, q) * duration**q / falling(N, q)
    m.setflags(write=False)
    return m


@lru_cache(maxsize=4096)
def _end_map_cached(duration: float) -> FloatArray:
    m = np.zeros((JET_ORDER, JET_ORDER))
    for k in range(JET_ORDER):
        row = JET_ORDER - 1 - k  # control point P^{9-k}, stored in order P^5..P^9
        for q in range(k + 1):
            m[row, q] = (-1) ** q * comb(k, q) * duration**q / falling(N, q)
    m.setflags(write=False)
    return m


def start_map(duration: float) -> FloatArray:
    """5x5 map: jet at u=0 -> control points P^0..P^4."""
    return _start_map_cached(float(duration))


def end_map(duration: float) -> FloatArray:
    """5x5 map: jet at u=1 -> control points P^5..P^9."""
    return _end_map_cached(float(duration))


def segment_from_jets(jet0: FloatArray, jet1: FloatArray, duration: float) -> FloatArray:
    """The unique degree-9 segment with the given end jets, shape (10, 3)."""
    return np.concatenate([start_map(duration) @ jet0, end_map(duration) @ jet1])


def segments_from_jets(jets: FloatArray, durations: FloatArray) -> FloatArray:
    """All segments of a trajectory from its waypoint jets (m, 5, 3): (m-1, 10, 3)."""
    d = np.asarray(durations, dtype=float)
    first_map, last_map, fall = _jet_ctrl_maps()
    scale = d[:, None] ** np.arange(JET_ORDER)[None, :] / fall[None, :]  # (s, 5)
    # P^k = sum_l binom(k, l) scale_l J_l: scale each jet's rows, then one shared (5, 5) map
    # (a matmul against a fixed map: ~5x faster than building a (5, 5) map per segment)
    first = np.matmul(first_map, scale[:, :, None] * jets[:-1])
    last = np.matmul(last_map, scale[:, :, None] * jets[1:])
    return np.concatenate([first, last], axis=1)


@lru_cache(maxsize=1)
def _jet_ctrl_maps() -> tuple[FloatArray, FloatArray, FloatArray]:
    """Lower-triangular binomials (rows P^0..P^4), the signed and reversed map for P^5..P^9,
    and the falling factorials N!/(N-i)!."""
    p = np.arange(JET_ORDER)
    binom = np.array([[comb(a, b) for b in range(JET_ORDER)] for a in range(JET_ORDER)], dtype=float)
    tri = binom * (p[None, :] <= p[:, None])
    last = (tri * ((-1.0) ** p)[None, :])[::-1]
    fall = np.array([falling(N, i) for i in range(JET_ORDER)], dtype=float)
    return tri, np.ascontiguousarray(last), fall


def start_jet(ctrl: FloatArray, duration: float) -> FloatArray:
    """Jet at u=0 of a segment, shape (5, 3)."""
    return np.stack(
        [ctrl[0]] + [hodograph(ctrl, k, duration)[0] for k in range(1, JET_ORDER)]
    )


def end_jet(ctrl: FloatArray, duration: float) -> FloatArray:
    """Jet at u=1 of a segment, shape (5, 3)."""
    return np.stack(
        [ctrl[-1]] + [hodograph(ctrl, k, duration)[-1] for k in range(1, JET_ORDER)]
    )


# --- subdivision ------------------------------------------------------------


def split_segment(ctrl: FloatArray, u: float) -> tuple[FloatArray, FloatArray]:
    """de Casteljau split at u: the two pieces' control points (exact curve)."""
    n = ctrl.shape[0] - 1
    work = np.array(ctrl, dtype=float)
    left = np.empty_like(work)
    right = np.empty_like(work)
    left[0] = work[0]
    right[n] = work[n]
    for r in range(1, n + 1):
        work = (1.0 - u) * work[:-1] + u * work[1:]
        left[r] = work[0]
        right[n - r] = work[-1]
    return left, right


@lru_cache(maxsize=32)
def _subdivision_cached(n: int, pieces: int) -> FloatArray:
    out = np.empty((pieces, n + 1, n + 1))
    for i in range(pieces):
        a, b = i / pieces, (i + 1) / pieces
        for r in range(n + 1):
            # blossom of the basis at (a x (n - r), b x r): control point r of the piece [a, b]
            work = np.eye(n + 1)
            for step in range(n):
                u = a if step < n - r else b
                work = (1.0 - u) * work[:-1] + u * work[1:]
            out[i, r] = work[0]
    out.setflags(write=False)
    return out


def subdivision_matrix(n: int, pieces: int) -> FloatArray:
    """(pieces, n+1, n+1): control points of the restriction of a degree-n Bézier curve to
    [i/pieces, (i+1)/pieces] are `M[i] @ ctrl` (de Casteljau splits are linear maps, so hull
    constraints on the pieces stay linear in the control points)."""
    if pieces < 1:
        raise ValueError(f"pieces: must be >= 1, got {pieces}")
    return _subdivision_cached(int(n), int(pieces))


@lru_cache(maxsize=32)
def _stacked_pieces(n: int, pieces: int) -> FloatArray:
    sub = subdivision_matrix(n, pieces)
    # piece i ends where piece i+1 starts (the same blossom, computed the same way): once
    out = np.ascontiguousarray(np.concatenate([sub[0]] + [sub[i, 1:] for i in range(1, pieces)]))
    out.setflags(write=False)
    return out


def stacked_pieces(n: int, pieces: int) -> FloatArray:
    """(pieces n + 1, n+1): the control points of all `pieces` equal de Casteljau pieces of a
    degree-n curve, each shared end once. Their hull holds the curve, and shrinks to it as
    pieces grow (the gap falls as 1 / pieces^2)."""
    return _stacked_pieces(int(n), int(pieces)) if pieces > 1 else np.eye(n + 1)


def certificate_matrix(k: int, pieces: int, duration: float = 1.0, n: int = N) -> FloatArray:
    """(pieces (n-k) + 1, n+1): control points -> the control points of the `pieces` pieces of
    the order-k hodograph. A bound on all of them is the planner's certificate of order k."""
    return np.asarray(stacked_pieces(n - k, pieces) @ hodograph_matrix(k, duration, n))


def subdivided_hull_extent(ctrl: FloatArray, k: int, durations: FloatArray, pieces: int) -> FloatArray:
    """(s, 2, 3) min and max over the order-k hodograph control points of every segment after
    splitting each hodograph into `pieces` equal pieces: the exact continuous-time certificate
    (the true extremes lie inside; pieces = 1 is the plain hull)."""
    h = hodographs(ctrl, k, durations)  # (s, 10-k, 3)
    sub = np.matmul(stacked_pieces(h.shape[1] - 1, pieces), h)  # (s, p (9-k) + 1, 3)
    return np.stack([sub.min(axis=1), sub.max(axis=1)], axis=1)


# --- trajectory evaluation --------------------------------------------------


def segments_at(times: FloatArray, t: FloatArray) -> NDArray[np.intp]:
    """The segment of knots `times` that each time of t lies in: the later one at a knot, the
    first before the span and the last at and after its end (where the curve holds its end)."""
    seg: NDArray[np.intp] = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    return seg


def segment_at(times: FloatArray, t: float) -> int:
    """`segments_at` for one time (a fraction of its cost: hot loops call this)."""
    return min(max(int(np.searchsorted(times, t, side="right")) - 1, 0), len(times) - 2)


def locate(times: FloatArray, t: FloatArray) -> tuple[NDArray[np.intp], FloatArray]:
    """Segment index and local parameter u for times t (clamped to the span)."""
    t = np.clip(np.atleast_1d(np.asarray(t, dtype=float)), times[0], times[-1])
    seg = segments_at(times, t)
    u = (t - times[seg]) / (times[seg + 1] - times[seg])
    return seg, np.clip(u, 0.0, 1.0)


def evaluate_trajectory(traj: Trajectory, t: FloatArray, order: int = 0) -> FloatArray:
    """Derivative `order` of a trajectory at times t: shape (len(t), 3) (or (3,) for scalar t)."""
    scalar = np.ndim(t) == 0
    seg, u = locate(traj.times, t)
    n = traj.control_points.shape[1] - 1
    if order > n:
        out = np.zeros((seg.shape[0], 3))
        return out[0] if scalar else out
    durations = np.diff(traj.times)
    if order == 0:
        pts = traj.control_points[seg]
    else:
        pts = hodographs(traj.control_points[seg], order, durations[seg])
    basis = bernstein_basis(n - order, u)  # (T, n-order+1)
    res: FloatArray = np.einsum("ti,tid->td", basis, pts)
    return res[0] if scalar else res


def trajectory_jet(traj: Trajectory, t: float) -> FloatArray:
    """Jet (position .. snap) at time t, shape (5, 3)."""
    return np.stack([evaluate_trajectory(traj, np.asarray(t, dtype=float), k) for k in range(JET_ORDER)])
