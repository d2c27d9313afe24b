"""Time allocation: waypoint times from segment lengths and derivative bounds.

The rule (`allocate_times`), for segment j of length L_j and direction u_j:

1. Directional bounds. Moving along u at speed v puts v|u_i| on axis i, so the
   usable speed is v_j = min_i bound_i / |u_i| (the smallest per-axis bound seen
   along the direction; the velocity bound on the side of travel, both sides
   for acceleration, jerk and snap, which act in both senses).
2. Waypoint speeds (a junction-speed pass, as in CNC/3-D printer planners):
   the speed through interior waypoint i is capped at
   min(v_{i-1}, v_i) * (1 + cos θ_i) / 2 for a turn of angle θ_i (full speed
   straight on, half at a right angle, zero for a reversal); the start speed is
   the initial velocity's component along u_0 (0 if None), the end speed 0.
   Forward and backward passes then enforce w_{i+1}^2 <= w_i^2 + 2 a L.
3. Trapezoid: each segment runs entry speed -> peak (<= v_j) -> exit speed at
   acceleration a_j; that is its kinematic time.
4. Higher orders: no rest-to-rest motion over L is faster than the bang-bang
   limits (32 L / j)^(1/3) (jerk) and (384 L / s)^(1/4) (snap); the segment's
   time is at least these.
5. Slack: the planner's curve is one degree-9 polynomial per segment, C^4 at
   the waypoints, with bounds imposed on hodograph control points (a
   sufficient, conservative condition). It cannot follow the bang-bang and
   trapezoid profiles, so the time above is multiplied by `safety`; the first
   and last segments start or end at rest with four derivatives pinned to
   zero, and get the extra factor `end_factor`.
6. An initial velocity across or against u_0 first has to be cancelled: the
   first segment gets |v0 - (v0.u_0)^+ u_0| / a_min more time (a_min the
   smallest per-axis acceleration bound).
7. Every duration is at least `min_duration`.

The defaults were tuned so that the global planner finds a verified plan on
random cluttered scenarios without hand tuning (tests/planner/test_timing.py
measures the rate).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner_core.problem import Bounds, FloatArray

DEFAULT_SAFETY = 1.6
DEFAULT_MIN_DURATION = 0.05  # seconds
_EPS = 1e-12
BoolArray = NDArray[np.bool_]
# Hodograph-hull necessary conditions, order k alone: T >= (C_k L / bound_k)^(1/k)
# with C_k = 9!/(9-k)! / g, g = max (p_9 - p_0) over scalar control points with
# |Δ^k p| <= 1 and the end pins (LP, see tests/planner/test_timing.py). An end is
# "rest" (all four derivatives zero: p_1..p_4 = p_0), "stop" (velocity zero,
# higher derivatives free) or "free". Table index [order-1, start, end] with
# 0 = rest, 1 = stop, 2 = free; 0 where the order alone does not limit T.
_HULL_C = np.array(
    [
        [[9.0, 2.25, 1.8], [2.25, 9.0 / 7.0, 1.125], [1.8, 1.125, 1.0]],
        [[72.0, 12.0, 4.8], [12.0, 4.5, 2.0], [4.8, 2.0, 0.0]],
        [[1008.0, 67.2, 14.4], [67.2, 12.0, 0.0], [14.4, 0.0, 0.0]],
        [[9072.0, 302.4, 43.2], [302.4, 0.0, 0.0], [43.2, 0.0, 0.0]],
    ]
)


def _directions(waypoints: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Segment lengths (s,) and unit directions (s, 3); zero-length segments get 0."""
    d = np.diff(waypoints, axis=0)
    lengths = np.linalg.norm(d, axis=1)
    units = np.where(lengths[:, None] > _EPS, d / np.maximum(lengths, _EPS)[:, None], 0.0)
    return lengths, units


def _symmetric(bounds: Bounds) -> FloatArray:
    """(4, 3): per order and axis, the bound that holds in both senses."""
    return np.minimum(bounds.hi, -bounds.lo)


def directional_bounds(bounds: Bounds, units: FloatArray) -> FloatArray:
    """(s, 4) usable magnitude of derivatives 1..4 along each unit direction.

    Velocity uses the bound on the side of travel; higher orders the
    two-sided bound. A zero direction gets the smallest axis bound.
    """
    hi = np.asarray(bounds.hi, dtype=float)
    lo = np.asarray(bounds.lo, dtype=float)
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
    with np.errstate(divide="ignore"):
        ratio = np.where(comp[:, None, :] > _EPS, per_axis / comp[:, None, :], np.inf)
    out = np.min(ratio, axis=2)
    zero = ~np.any(comp > _EPS, axis=1)
    out[zero] = np.min(sym, axis=1)
    return np.asarray(out)


def junction_speeds(units: FloatArray, vmax: FloatArray, start_speed: float) -> FloatArray:
    """(m,) speed caps at the waypoints from turn angles (rule 2, before the passes)."""
    caps = np.zeros(units.shape[0] + 1)
    caps[0] = min(max(start_speed, 0.0), float(vmax[0]))
    if units.shape[0] > 1:
        cos = np.clip(np.einsum("sd,sd->s", units[:-1], units[1:]), -1.0, 1.0)
        caps[1:-1] = np.minimum(vmax[:-1], vmax[1:]) * (1.0 + cos) / 2.0
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

    A pinned end is rest; otherwise the end interpolates between stop and free
    by its speed ratio w / vmax (velocity capacity is exactly linear in it).
    """
    rho = np.clip(speed / np.maximum(vmax, _EPS), 0.0, 1.0)
    w = np.stack([np.zeros_like(rho), 1.0 - rho, rho], axis=1)
    w[pinned] = (1.0, 0.0, 0.0)
    return np.asarray(w)


def hull_minimum(lengths: FloatArray, lim: FloatArray, start_w: FloatArray, end_w: FloatArray) -> FloatArray:
    """(s,) max over orders k of (C_k L / bound_k)^(1/k) with C_k from the end types."""
    coeffs = np.einsum("sa,kab,sb->sk", start_w, _HULL_C, end_w)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (coeffs * lengths[:, None] / lim) ** (1.0 / np.arange(1, 5))[None, :]
    return np.asarray(np.max(np.nan_to_num(t, posinf=0.0), axis=1))


def durations_from_lengths(
    waypoints: ArrayLike,
    bounds: Bounds,
    initial_velocity: ArrayLike | None = None,
    *,
    safety: float = DEFAULT_SAFETY,
    min_duration: float = DEFAULT_MIN_DURATION,
) -> FloatArray:
    """Segment durations (m-1,) by the rule in the module docstring."""
    wps = np.asarray(waypoints, dtype=float)
    if wps.ndim != 2 or wps.shape[1] != 3 or wps.shape[0] < 2:
        raise ValueError(f"waypoints: expected shape (m, 3) with m >= 2, got {wps.shape}")
    if not np.all(np.isfinite(wps)):
        raise ValueError("waypoints: contains non-finite values")
    if not (np.isfinite(safety) and safety >= 1.0):
        raise ValueError(f"safety: must be finite and >= 1, got {safety}")
    if not (np.isfinite(min_duration) and min_duration > 0.0):
        raise ValueError(f"min_duration: must be finite and > 0, got {min_duration}")
    v0 = np.zeros(3) if initial_velocity is None else np.asarray(initial_velocity, dtype=float)
    if v0.shape != (3,) or not np.all(np.isfinite(v0)):
        raise ValueError(f"initial_velocity: expected 3 finite numbers, got {np.asarray(v0).tolist()}")
    lengths, units = _directions(wps)
    lim = directional_bounds(bounds, units)  # (s, 4)
    vmax, amax = lim[:, 0], lim[:, 1]
    along = float(v0 @ units[0])
    caps = junction_speeds(units, vmax, along)
    w = _limit_by_acceleration(caps, lengths, amax)
    kinematic = trapezoid_durations(lengths, w[:-1], w[1:], vmax, amax)
    segs = lengths.shape[0]
    start_pinned = np.zeros(segs, dtype=bool)
    start_pinned[0] = not np.any(v0)
    end_pinned = np.zeros(segs, dtype=bool)
    end_pinned[-1] = True  # allocate_times plans to a stop at the last waypoint
    start_w = end_weights(w[:-1], vmax, start_pinned)
    end_w = end_weights(w[1:], vmax, end_pinned)
    base = np.maximum(kinematic, hull_minimum(lengths, lim, start_w, end_w))
    base[0] += float(np.linalg.norm(v0 - max(along, 0.0) * units[0])) / float(np.min(_symmetric(bounds)[1]))
    base *= safety
    return np.asarray(np.maximum(base, min_duration))


def allocate_times(
    waypoints: ArrayLike,
    bounds: Bounds,
    t0: float = 0.0,
    initial_velocity: ArrayLike | None = None,
    *,
    safety: float = DEFAULT_SAFETY,
    min_duration: float = DEFAULT_MIN_DURATION,
) -> FloatArray:
    """Waypoint times (m,), starting at t0, strictly increasing (see module docstring)."""
    if not np.isfinite(t0):
        raise ValueError(f"t0: must be finite, got {t0}")
    d = durations_from_lengths(
        waypoints, bounds, initial_velocity, safety=safety, min_duration=min_duration
    )
    return np.asarray(float(t0) + np.concatenate([[0.0], np.cumsum(d)]))
