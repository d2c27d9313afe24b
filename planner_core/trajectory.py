"""Trajectory surgery, one copy each: split, splice, trim, hold, and the fast sampler.

`Trajectory` itself (times, control points, corridors, evaluation) lives in
`planner_core.problem` and is re-exported here. Everything below is exact
(de Casteljau splits, identical control points) and pure: new trajectories
in, new trajectories out.
"""

from __future__ import annotations

import math

import numpy as np

from planner_core.bezier import end_jet, segment_at, segments_at, split_segment, start_jet
from planner_core.problem import FloatArray, Polytope, Trajectory

SPLIT_EPS = 1e-12  # a split closer than this (in seconds) to a boundary reuses that boundary


def split_at(traj: Trajectory, t: float) -> tuple[Trajectory, int]:
    """The trajectory with a segment boundary at t (exact de Casteljau) and that boundary's index.

    The curve is unchanged: segment j holding t becomes two segments (left on
    [times[j], t], right on [t, times[j+1]]); both halves keep segment j's
    corridor (the same object, duplicated), and `stats` is copied. Edge behaviour
    (nothing raises; `traj` itself is returned, unchanged, when no split is made):

    - t <= times[0] + 1e-12 (at or before the start): (traj, 0)
    - t >= times[-1] - 1e-12 (at or after the end): (traj, len(times) - 1)
    - |t - times[i]| < 1e-12 for an inner boundary i: (traj, i)
    - otherwise: (split trajectory, j + 1), with new.times[j + 1] == t.

    A caller that needs a new boundary strictly inside (as replan's
    `split_problem_at`) checks the index/identity or the span itself.
    """
    times = traj.times
    if t <= times[0] + SPLIT_EPS:
        return traj, 0
    if t >= times[-1] - SPLIT_EPS:
        return traj, len(times) - 1
    j = int(np.searchsorted(times, t, side="right") - 1)
    if abs(times[j] - t) < SPLIT_EPS:
        return traj, j
    u = (t - times[j]) / (times[j + 1] - times[j])
    left, right = split_segment(traj.control_points[j], u)
    ctrl = np.concatenate([traj.control_points[:j], left[None], right[None], traj.control_points[j + 1 :]])
    new_times = np.concatenate([times[: j + 1], [t], times[j + 1 :]])
    cors = None
    if traj.corridors is not None:
        cors = (*traj.corridors[: j + 1], traj.corridors[j], *traj.corridors[j + 1 :])
    return Trajectory(new_times, ctrl, cors, dict(traj.stats)), j + 1


def splice(old: Trajectory, new: Trajectory) -> Trajectory:
    """Old up to new.t0, then new. The caller guarantees the jets agree at new.t0."""
    if new.t0 > old.t_end + 1e-9:
        # The old plan ended at rest: fill the wait with a hold at its end point.
        end = old.control_points[-1, -1]
        filler = np.repeat(end[None, None, :], 10, axis=1)
        filled = None if old.corridors is None else (*old.corridors, None)
        old = Trajectory(np.append(old.times, new.t0), np.concatenate([old.control_points, filler]), filled, old.stats)
        head, k = old, old.n_segments
    elif new.t0 >= old.t_end - 1e-12:
        head, k = old, old.n_segments
    else:
        head, k = split_at(old, new.t0)
    ctrl = np.concatenate([head.control_points[:k], new.control_points])
    times = np.concatenate([head.times[:k], new.times])
    cors: tuple[Polytope | None, ...] | None = None
    if head.corridors is not None or new.corridors is not None:
        hc = head.corridors or (None,) * head.n_segments
        nc = new.corridors or (None,) * new.n_segments
        cors = (*hc[:k], *nc)
    # Keep the spliced trajectory short: pieces long past are never sampled again.
    # `spliced_at`: where the new plan begins; a reader of the whole (a client checking the
    # plan against its bounds) tells the flown history apart from the plan
    return Trajectory(times, ctrl, cors, {**new.stats, "spliced_at": float(new.t0)})


def trim_before(traj: Trajectory, t: float) -> Trajectory:
    """Drop whole segments that ended before t (never sampled again)."""
    k = int(np.searchsorted(traj.times, t, side="right")) - 2
    if k <= 0:
        return traj
    cors = None if traj.corridors is None else traj.corridors[k:]
    return Trajectory(traj.times[k:], traj.control_points[k:], cors, traj.stats)


def shifted(traj: Trajectory, dt: float) -> Trajectory:
    """The same curve `dt` s later: a plan from rest (a climb, a start from a hold) stays verified
    when its start moves, since nothing it is checked against (bounds, corridors) depends on the
    time."""
    return Trajectory(traj.times + float(dt), traj.control_points, traj.corridors, traj.stats)


def held_still(traj: Trajectory, t0: float, t1: float) -> bool:
    """Whether `traj` holds one point at rest from t0 to t1: a plan starting from it there may
    start anywhere in between (`shifted`)."""
    ts = np.linspace(t0, t1, 9)
    spread = float(np.ptp(traj.evaluate(ts), axis=0).max())
    moving = max(float(np.abs(traj.evaluate(ts, k)).max()) for k in (1, 2, 3, 4))
    return spread <= 1e-9 and moving <= 1e-9


def hold(position: FloatArray, t: float) -> Trajectory:
    """A verified-by-construction hold: all control points at a measured position."""
    ctrl = np.repeat(np.asarray(position, dtype=float).reshape(1, 1, 3), 10, axis=1)
    return Trajectory(times=np.array([t, t + 1.0]), control_points=ctrl, corridors=None, stats={"hold": True})


# --- the fast single-time sampler ------------------------------------------------


def _elevation(n: int) -> FloatArray:
    """(n+2, n+1) degree elevation n -> n+1 of a Bézier curve (exact: the same curve)."""
    e = np.zeros((n + 2, n + 1))
    i = np.arange(n + 2)
    e[i[1:], i[:-1]] = i[1:] / (n + 1)
    e[i[:-1], i[:-1]] = 1.0 - i[:-1] / (n + 1)
    return e


_DEG = 9
_BINOM = np.array([math.comb(_DEG, k) for k in range(_DEG + 1)], dtype=float)
_POW = np.arange(_DEG + 1, dtype=float)


def _raise_to_degree(k: int) -> FloatArray:
    """(10, 10-k): the order-k hodograph's control points (degree 9-k) raised to degree 9,
    times n!/(n-k)!, applied to the k-th differences of the control points."""
    m = np.eye(_DEG + 1 - k)
    for n in range(_DEG - k, _DEG):
        m = _elevation(n) @ m
    return m * math.perm(_DEG, k)


_RAISE = [_raise_to_degree(k) for k in range(5)]


class Sampler:
    """Position .. snap of one trajectory at single times, fast.

    The setpoint thread evaluates the active trajectory once per tick; the general
    `Trajectory.jet` (five vectorised evaluations over the whole trajectory) costs ~0.5 ms
    there, CPU a busy computer does not have. Each segment's hodographs of orders 0-4 are
    raised to degree 9 once, on first use, as one (10, 15) matrix (differences first, so a
    segment at rest gives exact zeros); a sample is then one Bernstein basis vector times
    that matrix (~15 µs).
    """

    def __init__(self, traj: Trajectory) -> None:
        self.traj = traj
        self.times = traj.times
        self.t0 = float(traj.times[0])
        self.t_end = float(traj.times[-1])
        self._segments: dict[int, FloatArray] = {}

    def _segment(self, s: int) -> FloatArray:
        m = self._segments.get(s)
        if m is None:
            ctrl = self.traj.control_points[s]
            d = float(self.times[s + 1] - self.times[s])
            m = np.hstack([_RAISE[k] @ np.diff(ctrl, k, axis=0) / d**k for k in range(5)])
            self._segments[s] = m
        return m

    def _eval(self, t: float, cols: int) -> FloatArray:
        tc = min(max(t, self.t0), self.t_end)
        s = segment_at(self.times, tc)
        t_lo, t_hi = float(self.times[s]), float(self.times[s + 1])
        u = min(max((tc - t_lo) / (t_hi - t_lo), 0.0), 1.0)
        basis = _BINOM * u**_POW * (1.0 - u) ** (_DEG - _POW)
        out: FloatArray = (basis @ self._segment(s)[:, :cols]).reshape(cols // 3, 3)
        return out

    def many(self, ts: FloatArray, order: int) -> FloatArray:
        """(len(ts), 3): derivative `order` (0-4) at each of the times ts, clamped to the span,
        as `Trajectory.evaluate` (the setpoints' low-passed acceleration takes ~100 a tick:
        ~10x cheaper here, from the same segment matrices as `jet`)."""
        tc = np.clip(np.asarray(ts, dtype=float), self.t0, self.t_end)
        seg = segments_at(self.times, tc)
        lo, hi = self.times[seg], self.times[seg + 1]
        u = np.clip((tc - lo) / (hi - lo), 0.0, 1.0)[:, None]
        basis = _BINOM * u**_POW * (1.0 - u) ** (_DEG - _POW)
        cols = slice(3 * order, 3 * order + 3)
        out: FloatArray
        if len(seg) and seg.min() == seg.max():  # one segment (the usual case): one product
            out = basis @ self._segment(int(seg[0]))[:, cols]
            return out
        out = np.empty((len(tc), 3))
        for s in np.unique(seg):
            rows = seg == s
            out[rows] = basis[rows] @ self._segment(int(s))[:, cols]
        return out

    def jet(self, t: float) -> FloatArray:
        """(5, 3) position .. snap at t clamped to the span, as `Trajectory.jet`."""
        return self._eval(t, 15)

    def jet3(self, t: float) -> FloatArray:
        """(3, 3): position, velocity, acceleration at t (clamped to the span; at rest past it)."""
        out = self._eval(t, 9)
        if t >= self.t_end:
            # Past the end the trajectory is at rest by construction; say so exactly.
            out[1:] = 0.0
        return out


_samplers: list[Sampler] = []


def sampler(traj: Trajectory) -> Sampler:
    """The Sampler of `traj`, kept for the last few trajectories (the active one and the one
    being swapped in); by identity, as trajectories are immutable."""
    for sm in _samplers:
        if sm.traj is traj:
            return sm
    sm = Sampler(traj)
    _samplers.insert(0, sm)
    del _samplers[3:]
    return sm


__all__ = [
    "Sampler",
    "Trajectory",
    "end_jet",
    "hold",
    "sampler",
    "splice",
    "split_at",
    "split_segment",
    "start_jet",
    "trim_before",
]
