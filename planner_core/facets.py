"""Which planes of many small bounded polytopes are facets, all at once.

Each polytope {x : A_g x <= b_g} (unit rows, the same number P of planes in one call)
is enumerated by plane triples in closed form (Cramer's rule with cross products, so
no per-triple solve), and plane p is a facet when the vertices on it span a
2-D face: the second singular value of the centred points on it exceeds the
tolerance (as `corridors._facet_mask` decides for one polytope). The vertices are
gathered into flat arrays first, so the per-plane statistics are `bincount`s over
(polytope, plane) keys instead of a Python loop per polytope.
"""

from __future__ import annotations

from functools import lru_cache
from itertools import combinations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

DET_TOL = 1e-12  # unit normals: |det| below this means three planes share no single point
_BATCH = 2_000_000  # polytopes x triples x planes per chunk (bounds the temporaries: ~16 MB each)


@lru_cache(maxsize=64)
def triples(k: int) -> IntArray:
    """All index triples i < j < l of range(k), (C(k, 3), 3), read-only."""
    idx = np.fromiter((i for t in combinations(range(k), 3) for i in t), dtype=np.intp).reshape(-1, 3)
    idx.setflags(write=False)
    return idx


def _scatter_eigs(key: IntArray, x: FloatArray, n_keys: int) -> tuple[FloatArray, FloatArray]:
    """Per key: the point count and the eigenvalues (ascending) of the centred scatter matrix."""
    count = np.bincount(key, minlength=n_keys).astype(float)
    safe = np.where(count > 0, count, 1.0)
    mean = np.stack([np.bincount(key, x[:, d], minlength=n_keys) for d in range(3)], axis=1) / safe[:, None]
    dx = x - mean[key]
    scatter = np.empty((n_keys, 3, 3))
    for a in range(3):
        for c in range(a, 3):
            scatter[:, a, c] = scatter[:, c, a] = np.bincount(key, dx[:, a] * dx[:, c], minlength=n_keys)
    return count, np.asarray(np.linalg.eigvalsh(scatter), dtype=float)


def facet_masks(A: FloatArray, b: FloatArray) -> BoolArray:
    """(G, P) facet flags of the polytopes {A_g x <= b_g}, A (G, P, 3) with unit rows, b (G, P).

    A polytope whose vertices do not span a solid (flat, empty or numerically so) gets
    every plane flagged: keeping planes is always safe.
    """
    G, P = b.shape
    out = np.ones((G, P), dtype=bool)
    if G == 0 or P < 4:
        return out
    T = triples(P)
    if P > 6 and np.array_equal(A[:, :3], -A[:, 3:6]):
        # planes a and a + 3 opposite (a box first, as corridors start): no triple with both meets
        tri = T
        par = np.zeros(tri.shape[0], dtype=bool)
        for a in range(3):
            par |= np.any(tri == a, axis=1) & np.any(tri == a + 3, axis=1)
        T = tri[~par]
    step = max(1, _BATCH // (T.shape[0] * P))
    for g0 in range(0, G, step):
        sl = slice(g0, min(G, g0 + step))
        out[sl] = _facets_chunk(A[sl], b[sl], T)
    return out


def _facets_chunk(A: FloatArray, b: FloatArray, T: IntArray) -> BoolArray:
    G, P = b.shape
    scale = np.maximum(1.0, np.max(np.abs(b), axis=1))  # (G,)
    # cross products of every plane pair, once: (G, P, P, 3)
    cross = np.cross(A[:, :, None, :], A[:, None, :, :])
    i, j, k = T[:, 0], T[:, 1], T[:, 2]
    c_jk, c_ki, c_ij = cross[:, j, k], cross[:, k, i], cross[:, i, j]  # (G, nT, 3)
    det = np.sum(A[:, i] * c_jk, axis=2)
    ok = np.abs(det) > DET_TOL
    x = b[:, i, None] * c_jk + b[:, j, None] * c_ki + b[:, k, None] * c_ij
    x /= np.where(ok, det, 1.0)[..., None]
    s = np.matmul(x, A.transpose(0, 2, 1)) - b[:, None, :]  # (G, nT, P)
    feasible = ok & np.all(s <= (1e-9 * scale)[:, None, None], axis=2)
    gv, tv = np.nonzero(feasible)
    xv = x[gv, tv]
    # a solid needs 4 vertices not in one plane
    n_v, eig_all = _scatter_eigs(gv, xv, G)
    tol = 1e-8 * scale
    solid = (n_v >= 4) & (np.sqrt(np.maximum(eig_all[:, 0], 0.0)) > tol)
    on = np.abs(s[gv, tv]) <= tol[gv, None]  # (Nv, P)
    v_idx, p_idx = np.nonzero(on)
    key = gv[v_idx] * P + p_idx
    cnt, eig = _scatter_eigs(key, xv[v_idx], G * P)
    face = (cnt >= 3) & (np.sqrt(np.maximum(eig[:, 1], 0.0)) > np.repeat(tol, P))
    return np.asarray(np.where(solid[:, None], face.reshape(G, P), True), dtype=bool)
