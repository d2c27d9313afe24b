"""One trajectory against many, in a few array operations: the others stacked once (`Packed`,
`pack`), the common intervals of every pair (`batch_knots`: the union of both knot sets on each
pair's overlap, exactly what `separation_pieces.common_knots` gives pair by pair) and each
interval located in its trajectory's segment (`locate_packed`, as `separation_pieces.locate`).

Why: against 200 neighbours the pair-by-pair loops (knots, location, splitting) cost ~40 us of
numpy call overhead per neighbour and call, more than the arithmetic itself; here every pair goes
through the same few calls. The results are the same numbers as pair by pair.

Pure numpy; no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from planner_core.problem import FloatArray, Trajectory
from planner_core.separation_pieces import KNOT_TOL, IntArray

PAD_MAX = 64  # knots per trajectory up to which `Packed` keeps them padded (a count, not a search)


@dataclass(frozen=True)
class Packed:
    """N trajectories stacked: trajectory k's knots are times[first[k]:first[k+1]], its segments
    ctrl[rows[k]:rows[k+1]] (rows[k] = first[k] - k)."""

    times: FloatArray  # (sum (S_k + 1),)
    first: IntArray  # (N + 1,)
    rows: IntArray  # (N + 1,)
    ctrl: FloatArray  # (sum S_k, 10, 3)
    lo: FloatArray  # (sum S_k, 3) each segment's control-point box
    hi: FloatArray
    t0: FloatArray  # (N,)
    t_end: FloatArray  # (N,)
    last: FloatArray  # (N, 3) the held last point
    padded: FloatArray | None = None  # (N, L) each trajectory's knots, +inf after; None if L > PAD_MAX

    @property
    def size(self) -> int:
        return int(self.t0.size)


def pack(trajs: Sequence[Trajectory]) -> Packed:
    if not trajs:
        z = np.zeros(0)
        return Packed(z, np.zeros(1, dtype=np.intp), np.zeros(1, dtype=np.intp), np.zeros((0, 10, 3)),
                      np.zeros((0, 3)), np.zeros((0, 3)), z, z, np.zeros((0, 3)))
    lens = np.array([t.times.size for t in trajs], dtype=np.intp)
    first = np.concatenate([[0], np.cumsum(lens)]).astype(np.intp)
    rows = first - np.arange(first.size, dtype=np.intp)
    ctrl = np.concatenate([t.control_points for t in trajs])
    times = np.concatenate([t.times for t in trajs])
    padded = None
    if int(lens.max()) <= PAD_MAX:
        padded = np.full((len(trajs), int(lens.max())), np.inf)
        padded[np.repeat(np.arange(len(trajs)), lens), np.arange(times.size) - np.repeat(first[:-1], lens)] = times
    return Packed(times, first, rows, ctrl, ctrl.min(axis=1), ctrl.max(axis=1), times[first[:-1]],
                  times[first[1:] - 1], ctrl[rows[1:] - 1, -1], padded)


def batch_knots(a: Trajectory, p: Packed, owners: IntArray, span: tuple[float, float] | None = None,
                extra: FloatArray | None = None) -> tuple[IntArray, FloatArray, FloatArray, IntArray]:
    """The common intervals of A against each p[owners[j]]: (pair j of each interval, t0, t1,
    intervals per pair), pairs in the given order and each pair's intervals in time order; the
    knots are `common_knots(a, others[owners[j]], extra, span)` (their overlap, cut to `span`,
    split at the union of both knot sets and `extra`, merged within KNOT_TOL, the last knot the
    span's end exactly)."""
    owners = np.asarray(owners, dtype=np.intp)
    lo = np.maximum(a.t0, p.t0[owners])
    hi = np.maximum(a.t_end, p.t_end[owners])
    if span is not None:
        lo, hi = np.maximum(lo, span[0]), np.minimum(hi, span[1])
    ours = a.times if extra is None else np.concatenate([a.times, np.asarray(extra, dtype=float)])
    return span_knots(lo, hi, p, owners, ours)


def span_knots(lo: FloatArray, hi: FloatArray, p: Packed, owners: IntArray,
               ours: FloatArray | None = None) -> tuple[IntArray, FloatArray, FloatArray, IntArray]:
    """`batch_knots` on given spans [lo[j], hi[j]] (none where hi <= lo): each span split at
    p[owners[j]]'s knots and the times `ours` within it, merged as `merge_knots` does."""
    owners = np.asarray(owners, dtype=np.intp)
    npair = owners.size
    live = hi > lo  # nothing in the span: one knot at most, no interval (as common_knots)
    nb = p.first[owners + 1] - p.first[owners]
    run = np.arange(int(nb.sum()), dtype=np.intp) - np.repeat(np.cumsum(nb) - nb, nb)
    pair_ids = np.arange(npair, dtype=np.intp)
    ours = np.zeros(0) if ours is None else ours
    t = np.concatenate([np.tile(ours, npair), p.times[np.repeat(p.first[owners], nb) + run], lo, hi])
    g = np.concatenate([np.repeat(pair_ids, ours.size), np.repeat(pair_ids, nb), pair_ids, pair_ids])
    inside = (t >= lo[g]) & (t <= hi[g]) & live[g]
    t, g = t[inside], g[inside]
    order = np.lexsort((t, g))
    t, g = t[order], g[order]
    if t.size == 0:
        return np.zeros(0, dtype=np.intp), t, t.copy(), np.zeros(npair, dtype=np.intp)
    # merge_knots per group: drop a knot within KNOT_TOL of the previous distinct one (duplicates
    # have diff 0, so the chain is the same as over the unique values), and the group's last kept
    # knot becomes its largest (the span's end stays exact)
    new = np.ones(t.size, dtype=bool)
    new[1:] = g[1:] != g[:-1]
    end = np.ones(t.size, dtype=bool)
    end[:-1] = new[1:]
    largest = np.zeros(npair)
    largest[g[end]] = t[end]
    keep = new.copy()
    keep[1:] |= np.diff(t) > KNOT_TOL
    t, g = t[keep], g[keep]
    end = np.ones(t.size, dtype=bool)
    end[:-1] = g[1:] != g[:-1]
    t[end] = largest[g[end]]
    same = g[1:] == g[:-1]
    pair = g[:-1][same]
    return pair, t[:-1][same], t[1:][same], np.bincount(pair, minlength=npair).astype(np.intp)


def locate_packed(p: Packed, owner: IntArray, t0: FloatArray,
                  t1: FloatArray) -> tuple[IntArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """`separation_pieces.locate` of each interval [t0[i], t1[i]] in p[owner[i]], for all at once:
    (row of its segment in p.ctrl, local u0, u1, held after the end). A binary search over each
    owner's own knots (a few vectorised steps: log2 of the longest), the same arithmetic after."""
    mid = 0.5 * (t0 + t1)
    base = p.first[owner]
    n = p.first[owner + 1] - base
    # searchsorted(times_k, mid, side="right"), per owner: a count against the padded knots where
    # every trajectory is short (three calls), else a binary search (a few calls per halving)
    if p.padded is not None:
        lo = (p.padded[owner] <= mid[:, None]).sum(axis=1)
    else:
        lo = np.zeros(owner.size, dtype=np.intp)
        hi = n.copy()
        for _ in range(int(np.ceil(np.log2(max(int(n.max(initial=1)), 1) + 1))) + 1):
            act = lo < hi
            if not act.any():
                break
            m = (lo + hi) // 2
            right = p.times[base + np.minimum(m, n - 1)] <= mid
            lo = np.where(act & right, m + 1, lo)
            hi = np.where(act & ~right, m, hi)
    seg = np.clip(lo - 1, 0, n - 2)
    ta = p.times[base + seg]
    d = p.times[base + seg + 1] - ta
    u0 = np.clip((t0 - ta) / d, 0.0, 1.0)
    u1 = np.clip((t1 - ta) / d, 0.0, 1.0)
    return p.rows[owner] + seg, u0, u1, t0 >= p.t_end[owner] - KNOT_TOL


GRID = 8  # our segments' boxes over runs of 1/GRID of their parameter (`span_boxes`)


@lru_cache(maxsize=4)
def _run_maps(grid: int) -> FloatArray:
    """(R, 10, 10) the restriction of a degree-9 segment to each run [i/grid, (j+1)/grid], i <= j
    (R = grid (grid+1)/2, in triu order), as weights on its control points: built once."""
    from planner_core.separation_pieces import restrict

    i, j = np.triu_indices(grid)
    return restrict(np.broadcast_to(np.eye(10), (i.size, 10, 10)), i / grid, (j + 1) / grid)


def span_boxes(traj: Trajectory, seg: IntArray, u0: FloatArray, u1: FloatArray, held: NDArray[np.bool_],
               grid: int = GRID) -> tuple[FloatArray, FloatArray]:
    """(lo, hi) (K, 3): a box holding the control points of traj's piece [u0[k], u1[k]] of segment
    seg[k] (`locate`'s answer; `held`: after the end, the held point), tighter than the whole
    segment's box: the box of the segment's restriction to the smallest run [i/grid, (j+1)/grid]
    of its grid that holds [u0, u1] (a piece's control points are convex combinations of those
    of any restriction holding it). The runs' boxes: one matmul of each segment used with the
    runs' fixed maps."""
    if seg.size == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    used, inv = np.unique(seg, return_inverse=True)
    maps = _run_maps(grid)
    nr = maps.shape[0]
    run = np.matmul(maps[None], traj.control_points[used][:, None])  # (U, R, 10, 3), one matmul
    rlo, rhi = run.min(axis=2).reshape(-1, 3), run.max(axis=2).reshape(-1, 3)
    # the 1e-9 slack keeps [u0, u1] inside the run whatever the rounding of u * grid
    i = np.clip(np.floor(u0 * grid - 1e-9), 0, grid - 1).astype(np.intp)
    j = np.clip(np.ceil(u1 * grid + 1e-9) - 1, 0, grid - 1).astype(np.intp)
    j = np.maximum(i, j)
    # index of run (i, j) in triu order: rows i' < i hold grid - i' runs each
    k = inv * nr + i * grid - (i * (i - 1)) // 2 + (j - i)
    lo, hi = rlo[k], rhi[k]
    if held.any():
        lo[held] = hi[held] = traj.control_points[-1, -1]
    return lo, hi


def our_boxes(traj: Trajectory, t0: FloatArray, t1: FloatArray,
              ) -> tuple[FloatArray, FloatArray, IntArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """The whole segment's box of each interval's piece of traj (the held point after its end)
    and `locate`'s (segment, u0, u1, held)."""
    from planner_core.separation_pieces import locate

    seg, u0, u1, held = locate(traj, t0, t1)
    ctrl = traj.control_points
    lo, hi = ctrl.min(axis=1)[seg], ctrl.max(axis=1)[seg]
    if held.any():
        lo[held] = hi[held] = ctrl[-1, -1]
    return lo, hi, seg, u0, u1, held
