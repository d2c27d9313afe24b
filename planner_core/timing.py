"""Time allocation: waypoint times from segment lengths and derivative bounds.

The rule (`allocate_times`), for segment j of length L_j and direction u_j:

1. Directional bounds. Moving along u at speed v puts v|u_i| on axis i, so the
   usable magnitude of derivative k is the smallest bound_i / |u_i| (velocity:
   the bound on the side of travel; acceleration, jerk, snap: both sides).
2. Effective acceleration. Jerk and snap slow down how fast acceleration
   builds: a_eff = v / (time of an S-curve from 0 to v with a, j, s).
3. Waypoint speeds (junction-speed passes, as in CNC/3-D printer planners):
   the speed through interior waypoint i is capped at
   min(v_{i-1}, v_i) ((1 + cos θ_i) / 2)^2 for a turn of angle θ_i (full speed
   straight on, 1/4 at a right angle, zero for a reversal; the square was
   measured better than the plain factor); start speed = initial velocity
   along u_0 (0 by default), end speed 0. Forward and backward passes enforce
   w_{i+1}^2 <= w_i^2 + 2 a_eff L.
4. Trapezoid: entry speed -> peak (<= v) -> exit speed at a_eff: the
   kinematic time.
5. Hull minimum: the planner bounds the control points of the de Casteljau
   pieces of the hodographs of one degree-9 polynomial per segment, which needs
   more time than a trapezoid,
   most of all at ends pinned at rest. Order k alone requires
   T >= (C_k L / bound_k)^(1/k), with C_k exact (an LP over scalar control
   points, table `_HULL_C`) for each pair of end types rest/stop/free; a
   junction of speed w interpolates between stop (w = 0) and free (w = v),
   the start (whole jet given) between rest and free.
   Both ends at rest give the exact minimum 2.64 L / v, sqrt(9.88 L / a),
   (98.2 L / j)^(1/3), (1008 L / s)^(1/4) of the fixed rest-to-rest curve certified
   on 3 pieces (9 L / v ... (9072 L / s)^(1/4) on one).
6. A start velocity across or against u_0 must be cancelled first: the first
   segment gets |v0 - (v0.u_0)^+ u_0| / a_min more (a_min: smallest axis bound).
7. Slack: the maximum of 4 and 5 (plus 6) times `safety` (turns, corridors and
   the coupling between orders are not in the model); at least `min_duration`.
8. With a moving start, the first segment's first five control points are
   fixed by the start jet and march outwards as T grows; if the first corridor
   is given, T_0 is capped where one of them would leave it.

The default safety was tuned on random cluttered scenes (3-11 waypoints, up
to 25 box obstacles, corridors from `corridors.build_corridors`, random
per-axis bounds, rest start). With safety 1 the smallest uniform factor that
made them feasible was at most 1.32 over 200 scenes for the iterative
planner without recovery (median 1.02, 95th percentile 1.18) and over 100 for
the global QP (95th percentile 1.21); at 1.4 every one of another 100 + 60
scenes planned (iterative without recovery, global).
tests/planner/test_timing.py re-measures this on fresh scenes.
"""

from __future__ import annotations

from collections.abc import Sequence
from math import comb

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner_core.problem import Bounds, FloatArray, Polytope

DEFAULT_SAFETY = 1.4  # measured, see the module docstring
DEFAULT_MIN_DURATION = 0.05  # seconds
_EPS = 1e-12
_HUGE = 1e12  # stands in for an unbounded derivative
BoolArray = NDArray[np.bool_]
# Certificate necessary conditions, order k alone: T >= (C_k L / bound_k)^(1/k) with
# C_k = 9!/(9-k)! / g, g = max (p_9 - p_0) over scalar control points whose order-k
# hodograph, split into constraints.HULL_PIECES (3) de Casteljau pieces, has every piece's
# control points in [-1, 1], with the end pins (LP, see tests/planner/test_timing.py). An
# end is "rest" (all four derivatives zero: p_1..p_4 = p_0), "stop" (velocity zero, higher
# derivatives free) or "free". Table index [order-1, start, end] with 0 = rest, 1 = stop,
# 2 = free; 0 where the order alone does not limit T. (One piece: 9, 72, 1008, 9072 at rest.)
_HULL_C = np.array(
    [
        [[1921 / 729, 1.614096757, 1.48375025], [1.614096757, 1.094225922, 1.052753683],
         [1.48375025, 1.052753683, 1.0]],
        [[800 / 81, 6.772532189, 3.281985832], [6.772532189, 4.356521739, 2.0], [3.281985832, 2.0, 0.0]],
        [[7952 / 81, 33.10335196, 9.119879367], [33.10335196, 12.0, 0.0], [9.119879367, 0.0, 0.0]],
        [[1008.0, 174.2354822, 31.11111111], [174.2354822, 0.0, 0.0], [31.11111111, 0.0, 0.0]],
    ]
)
_HULL_PIECES = 3  # the pieces the table is for (tests check it against constraints.HULL_PIECES)


def _directions(waypoints: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Segment lengths (s,) and unit directions (s, 3); zero-length segments get 0."""
    d = np.diff(waypoints, axis=0)
    lengths = np.linalg.norm(d, axis=1)
    units = np.where(lengths[:, None] > _EPS, d / np.maximum(lengths, _EPS)[:, None], 0.0)
    return lengths, units


def _symmetric(bounds: Bounds) -> FloatArray:
    """(4, 3): per order and axis, the bound that holds in both senses (a horizontal norm bound
    limits x and y too: `Bounds.axis_limits`)."""
    lo, hi = bounds.axis_limits()
    return np.minimum(hi, -lo)


def _norm_along(bounds: Bounds, units: FloatArray) -> FloatArray:
    """(s, 4) the largest magnitude along each unit direction that the horizontal norm bound's
    certifying polygon allows: r cos(pi / N) / max_i |n_i . u_xy| (exact for the polygon; inf
    where no norm bound or no horizontal component)."""
    from planner_core.constraints import polygon_normals

    reach = np.abs(units[:, :2] @ polygon_normals(bounds.sides).T).max(axis=1)  # (s,)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = bounds.polygon_radius[None, :] / reach[:, None]
    return np.asarray(np.where(reach[:, None] > _EPS, out, np.inf))


def directional_bounds(bounds: Bounds, units: FloatArray) -> FloatArray:
    """(s, 4) usable magnitude of derivatives 1..4 along each unit direction.

    Velocity uses the bound on the side of travel; higher orders the
    two-sided bound; a horizontal norm bound limits them too, through its polygon. A zero
    direction gets the smallest axis bound.
    """
    lo, hi = bounds.axis_limits()
    sym = _symmetric(bounds)
    if np.any(sym <= 0.0):
        order, axis = np.argwhere(sym <= 0.0)[0]
        raise ValueError(
            f"bounds: derivative {order + 1} on axis {axis} must allow both signs "
            f"(lo < 0 < hi), got [{lo[order, axis]}, {hi[order, axis]}]"
        )
    comp = np.abs(units)  # (s, 3)
    side = np.where(units >= 0.0, hi[0], -lo[0])  # (s, 3) velocity bound on the side of travel
    per_axis = np.concatenate(
        [side[:, None, :], np.broadcast_to(sym[1:], (units.shape[0], 3, 3))], axis=1
    )  # (s, 4, 3)
    with np.errstate(divide="ignore", over="ignore"):
        ratio = np.where(comp[:, None, :] > _EPS, per_axis / comp[:, None, :], np.inf)
    out = np.min(ratio, axis=2)
    if bounds.has_norm:
        out = np.minimum(out, _norm_along(bounds, units))
    zero = ~np.any(comp > _EPS, axis=1)
    out[zero] = np.min(sym, axis=1)
    return np.asarray(out)


def _ramp_time(delta: FloatArray, rate: FloatArray, rate_of_rate: FloatArray) -> FloatArray:
    """Time to raise a quantity by delta when its rate and the rate's rate are bounded (S-curve).

    A bound >= _HUGE counts as absent.
    """
    free_rate = rate >= _HUGE
    free_ror = rate_of_rate >= _HUGE
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        long = delta / rate + rate / rate_of_rate
        short = 2.0 * np.sqrt(delta / rate_of_rate)
        t = np.where(delta >= rate**2 / rate_of_rate, long, short)
    t = np.where(free_rate & ~free_ror, short, t)
    t = np.where(free_ror & ~free_rate, delta / rate, t)
    return np.asarray(np.where(free_rate & free_ror, 0.0, t))


def effective_acceleration(lim: FloatArray) -> FloatArray:
    """(s,) average acceleration of a jerk- and snap-limited ramp from 0 to full speed.

    Snap limits how fast jerk builds, so acceleration a is reached after
    ramp(a; j, s) and the effective jerk is a / that; full speed v is then
    reached after ramp(v; a, j_eff); v over that time is the trapezoid's
    acceleration (conservative for small speed changes).
    """
    v, a, j, s = lim.T
    ta = _ramp_time(a, j, s)
    j_eff = np.where(ta > 0.0, a / np.maximum(ta, _EPS), _HUGE)
    tv = _ramp_time(v, a, j_eff)
    a_eff = np.where(tv > 0.0, v / np.maximum(tv, _EPS), _HUGE)
    a_eff = np.where(v >= _HUGE, a, a_eff)  # no cruise speed: the ramp never ends
    return np.asarray(np.minimum(a_eff, a))


def junction_speeds(units: FloatArray, vmax: FloatArray, start_speed: float) -> FloatArray:
    """(m,) speed caps at the waypoints from turn angles (rule 2, before the passes)."""
    caps = np.zeros(units.shape[0] + 1)
    caps[0] = min(max(start_speed, 0.0), float(vmax[0]))
    if units.shape[0] > 1:
        cos = np.clip(np.einsum("sd,sd->s", units[:-1], units[1:]), -1.0, 1.0)
        caps[1:-1] = np.minimum(vmax[:-1], vmax[1:]) * ((1.0 + cos) / 2.0) ** 2
    return caps


def _limit_by_acceleration(caps: FloatArray, lengths: FloatArray, amax: FloatArray) -> FloatArray:
    w = caps.copy()
    reach = 2.0 * amax * lengths
    for i in range(lengths.shape[0]):
        w[i + 1] = min(w[i + 1], np.sqrt(w[i] ** 2 + reach[i]))
    for i in range(lengths.shape[0] - 1, -1, -1):
        w[i] = min(w[i], np.sqrt(w[i + 1] ** 2 + reach[i]))
    return w


def trapezoid_durations(
    lengths: FloatArray, entry: FloatArray, exit_: FloatArray, vmax: FloatArray, amax: FloatArray
) -> FloatArray:
    """Time to cover each length from entry to exit speed, peak <= vmax, |acc| <= amax.

    Assumes the speeds are reachable (|exit^2 - entry^2| <= 2 amax L).
    """
    peak = np.minimum(vmax, np.sqrt(np.maximum((2.0 * amax * lengths + entry**2 + exit_**2) / 2.0, 0.0)))
    peak = np.maximum(peak, np.maximum(entry, exit_))
    ramp = (2.0 * peak - entry - exit_) / amax
    ramp_dist = (2.0 * peak**2 - entry**2 - exit_**2) / (2.0 * amax)
    cruise = np.where(peak > _EPS, np.maximum(lengths - ramp_dist, 0.0) / np.maximum(peak, _EPS), 0.0)
    return np.asarray(ramp + cruise)


def end_weights(speed: FloatArray, vmax: FloatArray, pinned: BoolArray) -> FloatArray:
    """(s, 3) weights of the end types rest/stop/free for each segment end.

    By the speed ratio rho = w / vmax an end interpolates towards free: from
    stop at a junction, from rest at an end whose whole jet is given (the
    start, the goal), where acceleration, jerk and snap are pinned too.
    Velocity capacity is exactly linear in rho.
    """
    rho = np.clip(speed / np.maximum(vmax, _EPS), 0.0, 1.0)
    slow = 1.0 - rho
    zero = np.zeros_like(rho)
    w = np.stack([np.where(pinned, slow, zero), np.where(pinned, zero, slow), rho], axis=1)
    return np.asarray(w)


def hull_minimum(lengths: FloatArray, lim: FloatArray, start_w: FloatArray, end_w: FloatArray) -> FloatArray:
    """(s,) max over orders k of (C_k L / bound_k)^(1/k) with C_k from the end types."""
    coeffs = np.einsum("sa,kab,sb->sk", start_w, _HULL_C, end_w)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (coeffs * lengths[:, None] / lim) ** (1.0 / np.arange(1, 5))[None, :]
    return np.asarray(np.max(np.nan_to_num(t, posinf=0.0), axis=1))


def _fixed_points(jet: FloatArray, durations: FloatArray) -> FloatArray:
    """(G, 5, 3) control points P^0..P^4 fixed by a start jet, for each duration."""
    k = np.arange(5)[:, None]
    ell = np.arange(5)[None, :]
    binom = np.array([[comb(int(i), int(j)) for j in range(5)] for i in range(5)], dtype=float)
    falling = np.array([1.0, 9.0, 72.0, 504.0, 3024.0])
    coeff = np.where(ell <= k, binom / falling[None, :], 0.0)  # (5, 5)
    powers = durations[:, None] ** np.arange(5)[None, :]  # (G, 5)
    return np.asarray(np.einsum("kl,gl,ld->gkd", coeff, powers, jet))


def corridor_cap(jet: FloatArray, corridor: Polytope, t_hi: float, min_duration: float) -> float:
    """Largest T in [min_duration, t_hi] (on a grid) keeping the jet-fixed points in the corridor.

    Returns t_hi when they never leave it.
    """
    grid = np.geomspace(min_duration, t_hi, 64) if t_hi > min_duration else np.array([t_hi])
    pts = _fixed_points(jet, grid)  # (G, 5, 3)
    tol = 1e-9 * max(1.0, float(np.max(np.abs(corridor.b)))) if corridor.b.size else 0.0
    inside = np.all(pts @ np.asarray(corridor.A).T <= np.asarray(corridor.b) + tol, axis=(1, 2))
    if inside.all():
        return t_hi
    first_out = int(np.argmin(inside))
    return float(grid[first_out - 1]) if first_out > 0 else min_duration


def _start_jet(
    waypoints: FloatArray, initial_velocity: ArrayLike | None, initial_jet: ArrayLike | None
) -> FloatArray:
    jet = np.zeros((5, 3))
    jet[0] = waypoints[0]
    if initial_jet is not None:
        if initial_velocity is not None:
            raise ValueError("initial_velocity: give either initial_velocity or initial_jet, not both")
        given = np.asarray(initial_jet, dtype=float)
        if given.shape != (5, 3) or not np.all(np.isfinite(given)):
            raise ValueError(f"initial_jet: expected a finite (5, 3) array, got shape {given.shape}")
        jet[1:] = given[1:]
    elif initial_velocity is not None:
        v0 = np.asarray(initial_velocity, dtype=float)
        if v0.shape != (3,) or not np.all(np.isfinite(v0)):
            raise ValueError(f"initial_velocity: expected 3 finite numbers, got {v0.tolist()}")
        jet[1] = v0
    return jet


def _validated(waypoints: ArrayLike, safety: float, min_duration: float) -> FloatArray:
    wps = np.asarray(waypoints, dtype=float)
    if wps.ndim != 2 or wps.shape[1] != 3 or wps.shape[0] < 2:
        raise ValueError(f"waypoints: expected shape (m, 3) with m >= 2, got {wps.shape}")
    if not np.all(np.isfinite(wps)):
        raise ValueError("waypoints: contains non-finite values")
    if not (np.isfinite(safety) and safety >= 1.0):
        raise ValueError(f"safety: must be finite and >= 1, got {safety}")
    if not (np.isfinite(min_duration) and min_duration > 0.0):
        raise ValueError(f"min_duration: must be finite and > 0, got {min_duration}")
    return wps


def durations_from_lengths(
    waypoints: ArrayLike,
    bounds: Bounds,
    initial_velocity: ArrayLike | None = None,
    *,
    safety: float = DEFAULT_SAFETY,
    min_duration: float = DEFAULT_MIN_DURATION,
    initial_jet: ArrayLike | None = None,
    corridors: Sequence[Polytope | None] | None = None,
) -> FloatArray:
    """Segment durations (m-1,) by the rule in the module docstring.

    initial_jet (5, 3) replaces initial_velocity when the start also has
    acceleration, jerk or snap (its row 0 is ignored: the start is waypoint 0).
    corridors (one per segment, as in Problem) enables rule 8.
    """
    wps = _validated(waypoints, safety, min_duration)
    jet = _start_jet(wps, initial_velocity, initial_jet)
    v0 = jet[1]
    lengths, units = _directions(wps)
    lim = np.minimum(directional_bounds(bounds, units), _HUGE)  # (s, 4); unbounded -> huge
    vmax, amax = lim[:, 0], effective_acceleration(lim)
    along = float(v0 @ units[0])
    w = _limit_by_acceleration(junction_speeds(units, vmax, along), lengths, amax)
    kinematic = trapezoid_durations(lengths, w[:-1], w[1:], vmax, amax)
    segs = lengths.shape[0]
    start_pinned = np.zeros(segs, dtype=bool)
    start_pinned[0] = True  # the start jet is given in full
    end_pinned = np.zeros(segs, dtype=bool)
    end_pinned[-1] = True  # the plan ends at rest at the last waypoint
    hull = hull_minimum(lengths, lim, end_weights(w[:-1], vmax, start_pinned), end_weights(w[1:], vmax, end_pinned))
    base = np.maximum(kinematic, hull)
    a_min = float(np.min(np.minimum(_symmetric(bounds)[1], _HUGE)))
    base[0] += float(np.linalg.norm(v0 - max(along, 0.0) * units[0])) / a_min
    out = np.maximum(base * safety, min_duration)
    first = None if corridors is None else corridors[0]
    if first is not None and np.any(jet[1:]):
        out[0] = corridor_cap(jet, first, float(out[0]), min_duration)
    return np.asarray(out)


def allocate_times(
    waypoints: ArrayLike,
    bounds: Bounds,
    t0: float = 0.0,
    initial_velocity: ArrayLike | None = None,
    *,
    safety: float = DEFAULT_SAFETY,
    min_duration: float = DEFAULT_MIN_DURATION,
    initial_jet: ArrayLike | None = None,
    corridors: Sequence[Polytope | None] | None = None,
) -> FloatArray:
    """Waypoint times (m,), starting at t0, strictly increasing (see module docstring)."""
    if not np.isfinite(t0):
        raise ValueError(f"t0: must be finite, got {t0}")
    d = durations_from_lengths(
        waypoints,
        bounds,
        initial_velocity,
        safety=safety,
        min_duration=min_duration,
        initial_jet=initial_jet,
        corridors=corridors,
    )
    return np.asarray(float(t0) + np.concatenate([[0.0], np.cumsum(d)]))


def stop_to_stop_crossings(lengths: FloatArray, lim: FloatArray, fractions: FloatArray,
                           samples: int = 96) -> FloatArray:
    """(s, f) times at which the time-optimal stop-to-stop profile of each segment (length
    `lengths` (s,), straight, under `lim` (s, 4): the directional v, a, j, s) passes the
    fractions `fractions` (f,) of its length: the shape of its pieces' durations when the
    fastest allocation splits it with knots (allocation.fastest_durations).

    The profile is the jerk-limited S-curve (7 phases of constant jerk +-j_eff, 0) with snap
    folded into the jerk as `effective_acceleration` does: j_eff = a / (time to raise the
    acceleration to a under j and s), so a snap-limited ramp is as slow as the reference's.
    The peak speed is v when the segment is long enough for it, else the one whose
    accelerate-decelerate distance is the length (bisection: the distance grows with it).
    Times come from the profile sampled `samples` times per phase and interpolated.
    """
    v, a, j, s = np.asarray(lim, dtype=float).T
    ta_ramp = _ramp_time(a, j, s)
    j = np.where(ta_ramp > 0.0, a / np.maximum(ta_ramp, _EPS), j)
    j = np.minimum(j, _HUGE)
    L = np.maximum(np.asarray(lengths, dtype=float), _EPS)

    def phases(vp: FloatArray) -> tuple[FloatArray, FloatArray]:
        ap = np.minimum(a, np.sqrt(vp * j))
        tj = ap / j
        return tj, np.maximum(vp / np.maximum(ap, _EPS) - tj, 0.0)

    def distance(vp: FloatArray) -> FloatArray:
        tj, ta = phases(vp)
        return np.asarray(vp * (2.0 * tj + ta))

    vp = np.minimum(v, _HUGE).copy()
    short = distance(vp) > L
    lo, hi = np.zeros_like(vp), vp.copy()
    for _ in range(60):  # bisection on the peak speed of the segments too short to reach v
        mid = 0.5 * (lo + hi)
        over = distance(mid) > L
        hi = np.where(over, mid, hi)
        lo = np.where(over, lo, mid)
    vp = np.where(short, lo, vp)
    tj, ta = phases(vp)
    cruise = np.maximum(L - distance(vp), 0.0) / np.maximum(vp, _EPS)
    dur = np.stack([tj, ta, tj, cruise, tj, ta, tj], axis=1)  # (s, 7)
    jerk = j[:, None] * np.array([1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0])[None, :]
    u = np.linspace(0.0, 1.0, samples + 1)[1:]  # within a phase
    n_seg = L.shape[0]
    times = [np.zeros((n_seg, 1))]
    pos = [np.zeros((n_seg, 1))]
    p = np.zeros(n_seg)
    vel = np.zeros(n_seg)
    acc = np.zeros(n_seg)
    t0 = np.zeros(n_seg)
    for k in range(7):
        h = dur[:, k : k + 1] * u[None, :]  # (s, samples)
        jk = jerk[:, k : k + 1]
        pos.append(p[:, None] + vel[:, None] * h + acc[:, None] * h**2 / 2.0 + jk * h**3 / 6.0)
        times.append(t0[:, None] + h)
        d = dur[:, k]
        p, vel, acc = (p + vel * d + acc * d**2 / 2.0 + jerk[:, k] * d**3 / 6.0,
                       vel + acc * d + jerk[:, k] * d**2 / 2.0, acc + jerk[:, k] * d)
        t0 = t0 + d
    T = np.concatenate(times, axis=1)
    P = np.maximum.accumulate(np.concatenate(pos, axis=1) / L[:, None], axis=1)  # rounding: keep it monotone
    P[:, -1] = 1.0
    f = np.asarray(fractions, dtype=float)
    return np.stack([np.interp(f, P[i], T[i]) for i in range(n_seg)]) if n_seg else np.zeros((0, f.size))
