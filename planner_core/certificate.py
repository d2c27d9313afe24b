"""Per-duration segment maps and the certificate of rebuilt segments.

A local replan rebuilds a few segments from their end jets; before it is
returned, `certify_rebuilt` checks them (the control points of every
`HULL_PIECES` de Casteljau piece of the hodographs of orders 1..4 within bounds, every control point in its corridor, C^4
continuity with the kept neighbours) from maps built from the difference
matrices, independent of the QP's jet model. The maps depend on one
duration each and are cached: a replan touches a few durations, often the
same ones again.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import numpy as np

from planner_core.bezier import certificate_matrix, hodograph_matrix
from planner_core.constraints import HULL_PIECES, unit_templates
from planner_core.problem import (
    DEGREE,
    JET_ORDER,
    N_CTRL,
    ORDER_NAMES,
    Bounds,
    FloatArray,
    Polytope,
)

# --- per-duration maps (cached: a replan touches a few durations, often the same ones again) ---

# The d-dependence of every jet-space map below is a power law: an entry is its value at
# d = 1 times d**p for an integer p in -7..4 (hull maps -4..4, snap cost 1 - 2*4 + 0..8).
# One table of d's powers and a gather scale a whole precomputed layout, so a cache miss
# costs a few numpy calls instead of building matrices in Python loops.
# The row layout below (and `power_table`, `read_only`, `hodograph_limits`, `jet_rows`) is
# public: localqp builds its QP on the same certified rows, and must not copy this layout.
POWER_LO = -7
POWER_EXPONENTS = np.arange(POWER_LO, 5, dtype=float)
# the certified hodograph points: orders 1..4, each on HULL_PIECES de Casteljau pieces
_CERT_BLOCKS = tuple(certificate_matrix(k, HULL_PIECES) for k in range(1, 5))
ORDER_OF_ROW = np.concatenate([np.full(b.shape[0], k) for k, b in enumerate(_CERT_BLOCKS, start=1)])
# (2, 3 n): index of each hodograph value's lower (upper) bound in the 24 entries of (lo, hi) flattened
LIMIT_INDEX = np.stack([((ORDER_OF_ROW - 1)[:, None] * 3 + np.arange(3)).ravel() + 12 * side for side in (0, 1)])
HODO_ROWS = slice(N_CTRL, None)  # hull rows 10..: certified hodograph points of orders 1..4
INNER_POINTS = slice(1, DEGREE)  # control points P^1..P^8
N_HODO = int(ORDER_OF_ROW.size)  # certified hodograph points of orders 1..4 per segment


def power_table(d: float) -> FloatArray:
    """d ** POWER_EXPONENTS: index it by (power - POWER_LO)."""
    out: FloatArray = np.power(d, POWER_EXPONENTS)
    return out


def read_only(a: FloatArray) -> FloatArray:
    """`a`, made read-only in place (cached arrays are shared between callers)."""
    a.setflags(write=False)
    return a


def hodograph_limits(bounds: Bounds) -> FloatArray:
    """(2, n, 3): lower and upper bound of every certified hodograph point of orders 1..4."""
    return np.asarray(np.concatenate((bounds.lo, bounds.hi), axis=None)[LIMIT_INDEX].reshape(2, N_HODO, 3))


def _norm_excess(h: FloatArray, bounds: Bounds) -> FloatArray | None:
    """(..., n) how far each certified hodograph point (h (..., n, 3)) lies outside its order's
    horizontal polygon (`constraints.polygon_excess`; -inf where no norm bound), or None without
    a norm bound."""
    if not bounds.has_norm:
        return None
    from planner_core.constraints import polygon_excess

    return polygon_excess(h, bounds.horizontal[ORDER_OF_ROW - 1], bounds.sides)


@lru_cache(maxsize=1)
def jet_rows() -> tuple[FloatArray, FloatArray]:
    """(5, 5) maps from P^0..P^4 (resp. P^5..P^9) to the unscaled start (end) jet."""
    u0 = np.zeros((JET_ORDER, JET_ORDER))
    u1 = np.zeros((JET_ORDER, JET_ORDER))
    for k in range(JET_ORDER):
        h = hodograph_matrix(k, 1.0) if k else np.eye(DEGREE + 1)
        u0[k] = h[0, :JET_ORDER]
        u1[k] = h[-1, JET_ORDER:]
    u0.setflags(write=False)
    u1.setflags(write=False)
    return u0, u1


@lru_cache(maxsize=1)
def _cert_unit() -> tuple[FloatArray, FloatArray]:
    """The (n + 10, 10) certificate map at d = 1 and the power of d that scales each of its rows."""
    u0, u1 = jet_rows()
    unit = np.zeros((N_HODO + 2 * JET_ORDER, N_CTRL))
    unit[:N_HODO] = np.vstack(_CERT_BLOCKS)
    unit[N_HODO : N_HODO + JET_ORDER, :JET_ORDER] = u0
    unit[N_HODO + JET_ORDER :, JET_ORDER:] = u1
    order = np.concatenate([ORDER_OF_ROW, np.arange(JET_ORDER), np.arange(JET_ORDER)])
    return read_only(unit), read_only(-order.astype(float))


@lru_cache(maxsize=1024)
def _cert_map(d: float) -> FloatArray:
    """(n + 10, 10): control points -> certified hodograph points (rows 0..n-1), start jet, end jet.

    Built from the difference matrices, not from the jet maps the QP uses: the
    certificate stays independent of the model it checks.
    """
    unit, power = _cert_unit()
    return read_only(unit * (d**power)[:, None])


def _hodograph_stack(d: float) -> FloatArray:
    """(n, 10): control points -> certified hodograph points of orders 1..4, stacked."""
    return _cert_map(d)[:N_HODO]


_START_ROWS = slice(N_HODO, N_HODO + JET_ORDER)
_END_ROWS = slice(N_HODO + JET_ORDER, None)


def start_jet_of(ctrl: FloatArray, duration: float) -> FloatArray:
    """Jet (5, 3) at the start of a segment (10, 3), through the cached map."""
    return np.asarray(_cert_map(duration)[_START_ROWS].dot(ctrl))


def end_jet_of(ctrl: FloatArray, duration: float) -> FloatArray:
    return np.asarray(_cert_map(duration)[_END_ROWS].dot(ctrl))


@lru_cache(maxsize=1024)
def _ctrl_map(d: float) -> FloatArray:
    """(10, 10): a segment's end jets, stacked (J0; J1), -> its control points P^0..P^9."""
    q1, power, _, _ = unit_templates()
    return read_only(q1[:N_CTRL] * power_table(d)[power[:N_CTRL] - POWER_LO])


def segment_ctrl(jet0: FloatArray, jet1: FloatArray, duration: float) -> FloatArray:
    """bezier.segment_from_jets through a cached per-duration (10, 10) map."""
    return np.asarray(_ctrl_map(duration).dot(np.concatenate((jet0, jet1))))


# --- certificate ---------------------------------------------------------------


def _hull_failure_one(
    ctrl: FloatArray, d: float, lim: FloatArray, poly: Polytope | None, tol: float, name: int,
    bounds: Bounds | None = None,
) -> str | None:
    h = _hodograph_stack(d) @ ctrl  # (n, 3)
    worst = np.maximum(h - lim[1], lim[0] - h)
    w = float(worst.max())
    if not w <= tol:  # NaN fails too
        k = int(ORDER_OF_ROW[int(np.argmax(worst.max(axis=1)))])
        return f"{ORDER_NAMES[k]} bound exceeded by {w:.3g} on segment {name}"
    ex = None if bounds is None else _norm_excess(h, bounds)
    if ex is not None and not float(ex.max()) <= tol:
        k = int(ORDER_OF_ROW[int(np.argmax(ex))])
        return f"horizontal {ORDER_NAMES[k]} norm bound (polygon) exceeded by {float(ex.max()):.3g} on segment {name}"
    if poly is not None and poly.A.shape[0] > 0:
        v = float((ctrl @ poly.A.T - poly.b).max())
        if not v <= tol:
            return f"corridor violated by {v:.3g} on segment {name}"
    return None


def hull_violation(
    ctrl: FloatArray,
    durations: FloatArray,
    bounds: Bounds,
    corridors: Sequence[Polytope | None],
    tol: float = 1e-9,
    labels: Sequence[int] | None = None,
) -> str | None:
    """First hull certificate failure of segments (s, 10, 3), or None when all pass.

    Checks every certified hodograph point of orders 1..4 against the bounds (the box, and
    the horizontal norm's polygon) and all 10 control points against the corridor. `labels` are the segments'
    indices to name in the message (default 0..s-1). NaN never passes.
    """
    names = list(range(ctrl.shape[0])) if labels is None else list(labels)
    lim = hodograph_limits(bounds)
    for i in range(ctrl.shape[0]):
        msg = _hull_failure_one(ctrl[i], float(durations[i]), lim, corridors[i], tol, names[i], bounds)
        if msg is not None:
            return msg
    return None


def _take(arr: FloatArray, idx: Sequence[int]) -> FloatArray:
    """arr[idx] along the first axis; a view when idx is a run of consecutive indices."""
    if idx[-1] - idx[0] == len(idx) - 1:
        return arr[idx[0] : idx[-1] + 1]
    return arr[list(idx)]


def certify_rebuilt(
    ctrl: FloatArray,
    times: FloatArray,
    rebuild: Sequence[int],
    bounds: Bounds,
    corridors: Sequence[Polytope | None] | None,
    initial: FloatArray,
    final: FloatArray,
    *,
    tol: float = 1e-9,
    continuity_tol: float = 1e-6,
) -> str | None:
    """Certificate of the rebuilt segments of a trajectory, or the first failure's description.

    The hull certificate of each rebuilt segment (`hull_violation`), then C^4
    continuity (relative error) at both ends of each, against the kept
    neighbour or the problem's initial / final jet. Batched products over the
    rebuilt segments and their neighbours do the arithmetic: O(len(rebuild)).
    """
    if not rebuild:
        return None
    rebuild = sorted(rebuild)
    last = ctrl.shape[0] - 1
    segs = sorted({s + e for s in rebuild for e in (-1, 0, 1) if 0 <= s + e <= last})
    at = {s: i for i, s in enumerate(segs)}
    durs = [float(times[s + 1] - times[s]) for s in segs]
    Y = np.array([_cert_map(d) for d in durs]) @ _take(ctrl, segs)  # (k, n + 10, 3)
    h = _take(Y, [at[s] for s in rebuild])[:, :N_HODO]
    lim = hodograph_limits(bounds)
    hull_ok = float(np.maximum(h - lim[1], lim[0] - h).max()) <= tol
    ex = _norm_excess(h, bounds)
    if hull_ok and ex is not None:
        hull_ok = float(ex.max()) <= tol
    if hull_ok and corridors is not None:
        hull_ok = _corridors_hold(ctrl, rebuild, corridors, tol)
    if not hull_ok:  # name the first failure (in segment order, bounds before corridor)
        corr = [None if corridors is None else corridors[s] for s in rebuild]
        named = hull_violation(ctrl[rebuild], np.array([durs[at[s]] for s in rebuild]), bounds, corr, tol, rebuild)
        # the per-segment pass may round the other way at exactly the tolerance: still a failure
        return named or f"hull certificate failed at the tolerance on segments {rebuild}"
    joints = sorted({j for s in rebuild for j in (s, s + 1)})
    left = np.array([initial if j == 0 else Y[at[j - 1], _END_ROWS] for j in joints])
    right = np.array([final if j == last + 1 else Y[at[j], _START_ROWS] for j in joints])
    err = np.abs(left - right) / (1.0 + np.abs(left) + np.abs(right))
    if float(err.max()) <= continuity_tol:
        return None
    per = err.reshape(len(joints), -1).max(axis=1)
    i = int(np.flatnonzero(~(per <= continuity_tol))[0])  # NaN fails too
    return f"continuity broken at waypoint {joints[i]} (relative error {float(per[i]):.3g})"


def _corridors_hold(ctrl: FloatArray, segs: Sequence[int], corridors: Sequence[Polytope | None], tol: float) -> bool:
    """Every control point of each segment inside its corridor (NaN fails)."""
    polys = [p for p in (corridors[s] for s in segs) if p is not None and p.A.shape[0] > 0]
    if not polys:
        return True
    if len(polys) == len(segs) and len({p.A.shape[0] for p in polys}) == 1:  # one batched product
        A = np.array([p.A for p in polys])
        v = _take(ctrl, segs) @ A.transpose(0, 2, 1) - np.array([p.b for p in polys])[:, None, :]
        return float(v.max()) <= tol
    for s in segs:
        p = corridors[s]
        if p is not None and p.A.shape[0] > 0 and not float((ctrl[s] @ p.A.T - p.b).max()) <= tol:
            return False
    return True
