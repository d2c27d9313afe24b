"""Dropping planes that do not shape a corridor: non-facets and duplicates go, unless a plane
is the certificate that keeps an obstacle out (then it, or the plane restoring the most, stays)."""


from __future__ import annotations

import numpy as np

from planner_core.geometry.common import CERT_TOL, BoolArray, IntArray
from planner_core.geometry.polytopes import enumerate_vertices
from planner_core.problem import FloatArray


def _facet_mask(A: FloatArray, b: FloatArray, verts: FloatArray) -> BoolArray:
    """Planes of {A x <= b} that carry a 2-D face (the non-redundant ones)."""
    tol = 1e-8 * max(1.0, float(np.max(np.abs(b))))
    on = np.abs(verts @ A.T - b) <= tol  # (V, P)
    mask = np.zeros(A.shape[0], dtype=bool)
    for p in np.flatnonzero(on.sum(axis=0) >= 3):
        face = verts[on[:, p]]
        sv = np.linalg.svd(face - face.mean(axis=0), compute_uv=False)
        mask[p] = sv[1] > tol
    return mask


def _first_of_duplicates(A: FloatArray, b: FloatArray) -> BoolArray:
    """Drop planes parallel to a tighter (or identical earlier) one."""
    tol = 1e-9 * max(1.0, float(np.max(np.abs(b)))) if b.size else 0.0
    same = (A @ A.T) >= 1.0 - 1e-12
    idx = np.arange(A.shape[0])
    tighter = b[None, :] < b[:, None] - tol
    equal_earlier = (np.abs(b[None, :] - b[:, None]) <= tol) & (idx[None, :] < idx[:, None])
    return np.asarray(~np.any(same & (tighter | equal_earlier), axis=1), dtype=bool)


def prune_planes(
    A: FloatArray,
    b: FloatArray,
    certs: FloatArray,
    radius: float,
    aux: tuple[FloatArray, FloatArray] | None,
) -> IntArray:
    """Indices of the planes to keep: the facets, plus whatever restores certificates.

    certs (n_obstacles, P) holds each obstacle's margin beyond each plane.
    """
    keep = _first_of_duplicates(A, b)
    idx = np.flatnonzero(keep)
    Ak, bk = A[idx], b[idx]
    if aux is not None:
        Ak, bk = np.concatenate([Ak, aux[0]]), np.concatenate([bk, aux[1]])
    verts = enumerate_vertices(Ak, bk)
    if verts.shape[0] < 4:
        return idx  # numerically flat or empty: keeping planes is always safe
    facets = _facet_mask(Ak, bk, verts)[: idx.shape[0]]
    chosen = set(idx[facets].tolist())
    certifies = certs >= radius - CERT_TOL  # (n, P)
    certifies[:, ~keep] = False  # prefer survivors: a dropped duplicate has a kept twin
    chosen_mask = np.zeros(A.shape[0], dtype=bool)
    chosen_mask[list(chosen)] = True
    missing = ~np.any(certifies[:, chosen_mask], axis=1) & np.any(certifies, axis=1)
    while np.any(missing):
        # Greedy: the plane that restores the most certificates.
        p = int(np.argmax(certifies[missing].sum(axis=0)))
        chosen_mask[p] = True
        missing &= ~certifies[:, p]
    return np.flatnonzero(chosen_mask)


def mutual_certificates(verts: FloatArray, normals: FloatArray, offsets: FloatArray, r: float) -> BoolArray:
    """(G, K, K): candidate c (verts (G, K, V, 3)) is kept r away by candidate d's plane."""
    G, K, V, _ = verts.shape
    proj = np.matmul(verts.reshape(G, K * V, 3), normals.transpose(0, 2, 1)).reshape(G, K, V, K)
    return np.asarray(np.min(proj, axis=2) - offsets[:, None, :] >= r - CERT_TOL)


def greedy_planes(cert: BoolArray) -> BoolArray:
    """(G, K): the candidates (nearest first) that get a plane: those no earlier plane certifies."""
    G, K, _ = cert.shape
    added = np.zeros((G, K), dtype=bool)
    certified = np.zeros((G, K), dtype=bool)
    for i in range(K):
        need = np.flatnonzero(~certified[:, i])
        added[need, i] = True
        certified[need] |= cert[need, :, i]
    return added


def restore_certificates(keep: BoolArray, distinct: BoolArray, certs: list[BoolArray]) -> None:
    """Where pruning left a candidate without a plane that keeps it r away, keep planes again,
    greedily the one restoring the most (as `prune_planes`). keep, distinct: (G, Q) over the
    corridors' obstacle planes, updated in place; certs[g] (K_g, Q): which plane certifies
    which candidate."""
    G, Q = keep.shape
    width = max(c.shape[0] for c in certs)
    cert = np.zeros((G, width, Q), dtype=bool)
    for g, c in enumerate(certs):
        cert[g, : c.shape[0]] = c
    cert &= distinct[:, None, :]  # a dropped duplicate has a kept twin
    missing = ~np.any(cert & keep[:, None, :], axis=2) & np.any(cert, axis=2)
    for g in np.flatnonzero(np.any(missing, axis=1)).tolist():
        miss, cg = missing[g], cert[g]
        while np.any(miss):
            p = int(np.argmax(cg[miss].sum(axis=0)))
            keep[g, p] = True
            miss &= ~cg[:, p]



def first_of_duplicates_padded(A: FloatArray, b: FloatArray, valid: BoolArray) -> BoolArray:
    """`_first_of_duplicates` of every padded corridor at once: (n, K) rows to keep."""
    bmax = np.max(np.where(valid, np.abs(b), 0.0), axis=1, initial=0.0)
    tol = (1e-9 * np.maximum(1.0, bmax))[:, None, None]
    same = (np.einsum("nkd,nld->nkl", A, A) >= 1.0 - 1e-12) & valid[:, None, :] & valid[:, :, None]
    idx = np.arange(A.shape[1])
    tighter = b[:, None, :] < b[:, :, None] - tol
    equal_earlier = (np.abs(b[:, None, :] - b[:, :, None]) <= tol) & (idx[None, :] < idx[:, None])[None]
    return np.asarray(valid & ~np.any(same & (tighter | equal_earlier), axis=2), dtype=bool)
