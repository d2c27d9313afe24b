"""Pop-up obstacles (`update_corridors`): only corridors that no plane (box faces included)
already certifies against a new obstacle get new planes; the others are returned as they were."""


from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from planner_core.geometry.building import (
    BuildContext,
    add_planes,
    blocked_error,
    build_context,
    check_waypoints_clear,
    finish_corridor,
    pair_separations,
    separation_arrays,
    validate_radius,
    validate_waypoints,
)
from planner_core.geometry.common import CERT_TOL, BoolArray, IntArray
from planner_core.geometry.obstacles import (
    Obstacles,
    min_over_vertices,
    prepare_obstacles,
    segment_point_distance,
)
from planner_core.geometry.polytopes import normalised
from planner_core.geometry.pruning import first_of_duplicates_padded
from planner_core.problem import FloatArray, Polytope


def update_corridors(
    waypoints: ArrayLike,
    corridors: Sequence[Polytope],
    obstacles: Sequence[Polytope],
    new_obstacles: Sequence[Polytope],
    map_box: tuple[ArrayLike, ArrayLike] | None,
    radius: float,
    *,
    prune: bool = True,
) -> tuple[tuple[Polytope, ...], list[int]]:
    """Add pop-up obstacles to existing corridors, touching affected segments only.

    A segment is affected when no plane of its corridor already keeps a new
    obstacle radius away (the certificate test: conservative, it may rebuild a
    corridor that merely comes close, never skips one that overlaps). Affected
    corridors get a maximum-margin plane per uncertified new obstacle and are
    pruned again; the others are returned as the very same objects. New
    obstacles are numbered after `obstacles` in errors.

    prune=False (the in-flight fast path): affected corridors only get the new
    planes appended, plus the cheap removal of parallel looser duplicates. The
    region, containment and every certificate are exactly those of the pruned
    result; planes that stopped being facets are kept (a few redundant QP rows),
    which skips the vertex enumeration (~2 ms a corridor) and the preparation
    of the old obstacles, which then are only counted. It runs over all
    affected corridors at once (same planes, order and errors as one corridor
    at a time): a pop-up on map-box-only corridors affects every one of them.
    """
    wps = validate_waypoints(waypoints)
    r = validate_radius(radius)
    if len(corridors) != wps.shape[0] - 1:
        raise ValueError(f"corridors: expected {wps.shape[0] - 1} (one per segment), got {len(corridors)}")
    new = prepare_obstacles(new_obstacles, first_index=len(obstacles))
    if prune:
        everyone = prepare_obstacles([*obstacles, *new_obstacles])
        ctx = build_context(wps, new, map_box, r, first_index=len(obstacles), all_obs=everyone)
        full = BuildContext(wps, everyone, r, ctx.map_A, ctx.map_b, ctx.aux, 0)
    else:
        ctx = build_context(wps, new, None, r, first_index=len(obstacles))
    check_waypoints_clear(ctx)
    A_all, b_all, starts = _stack_corridors(corridors)
    out = list(corridors)
    changed: list[int] = []
    if new.n == 0:
        return tuple(out), changed
    certified = _certified_by_corridors(new, A_all, b_all, starts, r)  # (n_new, corridors)
    affected = np.flatnonzero(~np.all(certified, axis=0))
    if affected.size == 0:
        return tuple(out), changed
    lower = np.maximum(segment_point_distance(wps[:-1], wps[1:], new.centres) - new.radii, 0.0)
    # the uncertified (segment, new obstacle) pairs need a plane, unless an earlier new plane of
    # the same corridor certifies them: their separations, batched per obstacle
    ks, js = np.nonzero(~certified[:, affected])
    if not prune:
        polys = _append_planes(ctx, affected, A_all, b_all, starts, certified, lower, (js, ks))
        for j, poly in zip(affected.tolist(), polys, strict=True):
            out[j] = poly
        return tuple(out), affected.tolist()
    seps = pair_separations(ctx, affected[js], ks)
    for j in affected.tolist():
        A, b = A_all[starts[j] : starts[j + 1]], b_all[starts[j] : starts[j + 1]]
        order = np.argsort(lower[j], kind="stable")
        A2, b2 = add_planes(ctx, j, A, b, order, np.zeros(new.n, dtype=bool), seps)
        out[j] = finish_corridor(full, A2, b2)
        changed.append(j)
    return tuple(out), changed


def _stack_corridors(corridors: Sequence[Polytope]) -> tuple[FloatArray, FloatArray, IntArray]:
    """Every corridor's unit rows stacked, and where each corridor starts (len + 1 offsets).

    Checks as `normalised` does, naming the first bad corridor, without a Python pass
    of array operations per corridor (a long mission has a thousand of them).
    """
    As = [np.asarray(c.A, dtype=float) for c in corridors]
    bs = [np.asarray(c.b, dtype=float) for c in corridors]
    for j, (A, b) in enumerate(zip(As, bs, strict=True)):
        if A.ndim != 2 or A.shape[1] != 3 or b.shape != (A.shape[0],):
            normalised(corridors[j], f"corridors[{j}]")  # raises, with the reason
    counts = np.array([A.shape[0] for A in As], dtype=np.intp)
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.intp)
    A_all = np.concatenate(As) if As else np.zeros((0, 3))
    b_all = np.concatenate(bs) if bs else np.zeros(0)
    norms = np.linalg.norm(A_all, axis=1)
    bad = ~(np.all(np.isfinite(A_all), axis=1) & np.isfinite(b_all)) | (norms <= 1e-12)
    if np.any(bad):
        j = int(np.searchsorted(starts, int(np.argmax(bad)), side="right") - 1)
        normalised(corridors[j], f"corridors[{j}]")  # raises, with the reason
    return A_all / norms[:, None], b_all / norms, starts


def _certified_by_corridors(
    obs: Obstacles, A_all: FloatArray, b_all: FloatArray, starts: IntArray, radius: float
) -> BoolArray:
    """(n, corridors): some plane of the corridor keeps obstacle k radius away."""
    n_cor = starts.shape[0] - 1
    out = np.zeros((obs.n, n_cor), dtype=bool)
    rows = obs.margins(A_all, b_all) >= radius - CERT_TOL  # (n, R)
    nonempty = np.flatnonzero(starts[1:] > starts[:-1])
    if nonempty.size:
        out[:, nonempty] = np.logical_or.reduceat(rows, starts[nonempty], axis=1)
    return out


def _append_planes(
    ctx: BuildContext,
    affected: IntArray,
    A_all: FloatArray,
    b_all: FloatArray,
    starts: IntArray,
    certified: BoolArray,
    lower: FloatArray,
    pairs: tuple[IntArray, IntArray],
) -> list[Polytope]:
    """The unpruned update of every affected corridor at once: `add_planes` (nearest new
    obstacle first, a plane for each one still uncertified) then `_first_of_duplicates`,
    as array operations over corridors; the only Python loop is over new obstacles.

    pairs: (rows into `affected`, obstacles) of the uncertified pairs, whose separations
    are computed here in one batch per obstacle; a plane is only ever needed for them.
    """
    obs, r = ctx.obs, ctx.radius
    n_aff, n_new = affected.shape[0], obs.n
    pa, pk = pairs
    normals, gaps = separation_arrays(ctx, affected[pa], pk)
    pair_of = np.full((n_aff, n_new), -1, dtype=np.intp)
    pair_of[pa, pk] = np.arange(pa.shape[0])
    orders = np.argsort(lower[affected], axis=1, kind="stable")  # (n_aff, n_new), nearest first
    cert = certified[:, affected].T.copy()  # (n_aff, n_new)
    new_A = np.zeros((n_aff, n_new, 3))  # by round
    new_b = np.zeros((n_aff, n_new))
    added = np.zeros((n_aff, n_new), dtype=bool)
    blocked_at = np.full(n_aff, n_new, dtype=np.intp)  # first round whose plane does not exist
    every = np.arange(n_aff)
    for i in range(n_new):
        k = orders[:, i]
        need = np.flatnonzero(~cert[every, k] & (blocked_at == n_new))
        if need.size == 0:
            continue
        p = pair_of[need, k[need]]
        n, g = normals[p], gaps[p]
        bad = np.isnan(n[:, 0]) | (g < 2.0 * r)
        blocked_at[need[bad]] = i
        need, n, kk = need[~bad], n[~bad], k[need[~bad]]
        off = min_over_vertices(obs, n, kk) - r
        new_A[need, i], new_b[need, i], added[need, i] = n, off, True
        cert[need] |= (obs.margins(n, off) >= r - CERT_TOL).T
    if np.any(blocked_at < n_new):
        a = int(np.argmax(blocked_at < n_new))
        k0 = int(orders[a, blocked_at[a]])
        raise blocked_error(ctx, int(affected[a]), k0, float(gaps[pair_of[a, k0]]))
    A_pad, b_pad, valid = _padded_corridors(affected, A_all, b_all, starts, new_A, new_b, added)
    keep = first_of_duplicates_padded(A_pad, b_pad, valid)
    return [
        Polytope(A=np.ascontiguousarray(A_pad[a, keep[a]]), b=np.ascontiguousarray(b_pad[a, keep[a]]))
        for a in range(n_aff)
    ]



def _padded_corridors(
    affected: IntArray,
    A_all: FloatArray,
    b_all: FloatArray,
    starts: IntArray,
    new_A: FloatArray,
    new_b: FloatArray,
    added: BoolArray,
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Each affected corridor's old rows then its added rows, padded: (n, K, 3), (n, K), valid."""
    n_aff = affected.shape[0]
    n_old = starts[affected + 1] - starts[affected]
    total = n_old + added.sum(axis=1)
    width = int(total.max()) if n_aff else 0
    A_pad = np.zeros((n_aff, width, 3))
    b_pad = np.zeros((n_aff, width))
    owner = np.repeat(np.arange(n_aff), n_old)
    pos = np.arange(owner.shape[0]) - np.repeat(np.cumsum(n_old) - n_old, n_old)
    src = starts[affected][owner] + pos
    A_pad[owner, pos], b_pad[owner, pos] = A_all[src], b_all[src]
    a, i = np.nonzero(added)
    slot = n_old[a] + np.cumsum(added, axis=1)[a, i] - 1
    A_pad[a, slot], b_pad[a, slot] = new_A[a, i], new_b[a, i]
    valid = np.arange(width)[None, :] < total[:, None]
    return A_pad, b_pad, valid
