"""Broad phase: which axis-aligned boxes overlap which, without testing every pair.

A sorted sweep along one axis (numpy `searchsorted`): boxes sorted by their lower
end; a query box can only overlap those whose lower end lies in
[query lo - widest box, query hi), a contiguous run of the sorted order, which is
then tested exactly. Boxes much wider than the typical one would widen every run,
so they are set apart and tested against every query (there are few of them).

Chosen over `scipy.spatial.cKDTree` (Chebyshev ball queries) because the queries
are boxes, not balls, the runs are a handful of array operations for every query
at once, and importing scipy.spatial costs ~0.5 s of a cold start; over a uniform
grid because the run needs no cell size to tune. The sweep runs along the axis the
boxes spread most over, so a run holds a thin slab of the scene.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]

DENSE_PAIRS = 4096  # below this many pairs, test them all (the sweep's set-up costs more)
WIDE = 4.0  # a box wider than WIDE x the median width along the sweep axis is tested apart


def _overlap(qlo: FloatArray, qhi: FloatArray, olo: FloatArray, ohi: FloatArray) -> NDArray[np.bool_]:
    return np.asarray(np.all((olo < qhi) & (ohi > qlo), axis=-1))


def overlapping_pairs(qlo: FloatArray, qhi: FloatArray, olo: FloatArray, ohi: FloatArray) -> tuple[IntArray, IntArray]:
    """(query i, box k) for every query box [qlo_i, qhi_i] (q, 3) that overlaps box [olo_k, ohi_k]
    (n, 3) with positive volume (open intervals: touching faces do not count). Sorted by query
    then box index."""
    nq, n = qlo.shape[0], olo.shape[0]
    if nq == 0 or n == 0:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    if nq * n <= DENSE_PAIRS:
        qi, ok = np.nonzero(_overlap(qlo[:, None], qhi[:, None], olo[None], ohi[None]))
        return qi.astype(np.intp), ok.astype(np.intp)
    axis = int(np.argmax(np.ptp(np.concatenate([olo, ohi]), axis=0)))
    width = ohi[:, axis] - olo[:, axis]
    wide = width > WIDE * max(float(np.median(width)), 1e-12)
    parts_q: list[IntArray] = []
    parts_k: list[IntArray] = []
    narrow = np.flatnonzero(~wide)
    if narrow.size:
        order = narrow[np.argsort(olo[narrow, axis], kind="stable")]
        starts = olo[order, axis]
        wmax = float(width[narrow].max())
        i0 = np.searchsorted(starts, qlo[:, axis] - wmax, side="left")
        i1 = np.searchsorted(starts, qhi[:, axis], side="left")
        counts = np.maximum(i1 - i0, 0)
        total = int(counts.sum())
        if total:
            q = np.repeat(np.arange(nq, dtype=np.intp), counts)
            first = np.repeat(np.cumsum(counts) - counts, counts)
            k = order[np.repeat(i0, counts) + np.arange(total) - first]
            hit = _overlap(qlo[q], qhi[q], olo[k], ohi[k])
            parts_q.append(q[hit])
            parts_k.append(k[hit])
    big = np.flatnonzero(wide)
    if big.size:
        qi, bi = np.nonzero(_overlap(qlo[:, None], qhi[:, None], olo[big][None], ohi[big][None]))
        parts_q.append(qi.astype(np.intp))
        parts_k.append(big[bi])
    if not parts_q:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    q_all, k_all = np.concatenate(parts_q), np.concatenate(parts_k)
    order = np.lexsort((k_all, q_all))
    return q_all[order], k_all[order]


def count_beyond(values: FloatArray, thresholds: FloatArray, upper: bool) -> IntArray:
    """How many of `values` are >= each threshold (upper) or <= it (not upper)."""
    s = np.sort(values)
    if upper:
        return np.asarray(s.size - np.searchsorted(s, thresholds, side="left"), dtype=np.intp)
    return np.asarray(np.searchsorted(s, thresholds, side="right"), dtype=np.intp)
