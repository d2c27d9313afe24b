"""Relax-and-check diagnosis of an infeasible jet QP.

Drop one constraint group at a time (bounds of order k of segment s, or the
corridor of segment s), re-solve for feasibility only, and report the groups
whose removal makes the QP feasible. Slow by design (one QP per group); only
run after a failure.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from planner_core.constraints import INF, KIND_BOUND
from planner_core.jets import ProblemCache, assemble, group_name
from planner_core.problem import FloatArray, Problem
from planner_core.qp import solve_lp, solve_qp
from planner_core.result import Diagnosis


def diagnose(
    problem: Problem,
    jets: FloatArray,
    free: Sequence[int],
    *,
    open_end: bool = False,
    cache: ProblemCache | None = None,
) -> Diagnosis:
    cache = cache if cache is not None and cache.problem is problem else ProblemCache(problem)
    waypoint = min(free)
    n_seg = problem.m - 1
    base = assemble(cache, jets, free, open_end=open_end)
    if base.constant_violation:
        s, kind, order, _ = base.constant_violation[0]
        name = group_name(s, kind, order, n_seg)
        if s == 0 and waypoint == 1:
            name += " fixed by the initial state"
        return Diagnosis(waypoint, s, name, "bounds" if kind == KIND_BOUND else "corridor", order or None, (name,))
    keys = list(zip(base.row_segment.tolist(), base.row_kind.tolist(), base.row_order.tolist(), strict=True))
    groups = sorted(set(keys))
    slack = _elastic_slack(base.G, base.lo, base.hi, keys, groups)
    helpful: list[tuple[int, int, int]] = []
    for g in groups:
        qp = assemble(cache, jets, free, open_end=open_end, drop=frozenset([g]))
        if _feasible(qp.G, qp.lo, qp.hi):
            helpful.append(g)
    if helpful:
        helpful.sort(key=lambda g: -slack.get(g, 0.0))
        names = tuple(group_name(s, k, o, n_seg) for s, k, o in helpful)
        s, k, o = helpful[0]
        return Diagnosis(waypoint, s, names[0], "bounds" if k == KIND_BOUND else "corridor", o or None, names)
    # no single group: name the group that needs the largest relative relaxation
    ranked = sorted((g for g in groups if slack.get(g, 0.0) > 1e-9), key=lambda g: -slack[g])
    if not ranked:
        return Diagnosis(waypoint, None, "the QP solver failed without a clear culprit", "unknown")
    names = tuple(group_name(s, k, o, n_seg) for s, k, o in ranked)
    s, k, o = ranked[0]
    others = "; ".join(names[1:4])
    label = f"{names[0]} (needs relaxation {slack[ranked[0]]:.3g}" + (f"; also {others})" if others else ")")
    return Diagnosis(waypoint, s, label, "bounds" if k == KIND_BOUND else "corridor", o or None, names)


def _feasible(G: FloatArray | sp.csc_matrix, lo: FloatArray, hi: FloatArray) -> bool:
    n = G.shape[1]
    return solve_qp(np.eye(n), np.zeros(n), G, lo, hi, "daqp").ok


def _elastic_slack(
    G: FloatArray | sp.csc_matrix,
    lo: FloatArray,
    hi: FloatArray,
    keys: list[tuple[int, int, int]],
    groups: list[tuple[int, int, int]],
) -> dict[tuple[int, int, int], float]:
    """Smallest relaxation per group (one slack per group, rows normalised), by LP (HiGHS, `qp.solve_lp`)."""
    Gd = np.asarray(G.toarray()) if isinstance(G, sp.spmatrix | sp.sparray) else np.asarray(G)
    n, ng = Gd.shape[1], len(groups)
    gi = {g: i for i, g in enumerate(groups)}
    col = np.array([gi[k] for k in keys], dtype=np.int64)
    up = hi < INF
    dn = lo > -INF
    A = np.vstack([Gd[up], -Gd[dn]])
    b = np.concatenate([hi[up], -lo[dn]])
    cols = np.concatenate([col[up], col[dn]])
    norms = np.linalg.norm(A, axis=1)
    norms[norms == 0] = 1.0
    A, b = A / norms[:, None], b / norms
    E = np.zeros((A.shape[0], ng))
    E[np.arange(A.shape[0]), cols] = 1.0
    res = solve_lp(
        np.concatenate([np.zeros(n), np.ones(ng)]),
        np.hstack([A, -E]),
        b,
        [(None, None)] * n + [(0, None)] * ng,
    )
    if not res.ok or res.x is None:
        return {}
    return {g: float(res.x[n + i]) for g, i in gi.items()}


def elastic_segments(problem: Problem, jets: FloatArray, free: Sequence[int], *, open_end: bool,
                     cache: ProblemCache | None = None) -> list[int]:
    """Segments whose constraints must be relaxed to make the QP feasible (for time stretching)."""
    cache = cache if cache is not None and cache.problem is problem else ProblemCache(problem)
    qp = assemble(cache, jets, free, open_end=open_end)
    if qp.constant_violation:
        return sorted({s for s, *_ in qp.constant_violation})
    keys = list(zip(qp.row_segment.tolist(), qp.row_kind.tolist(), qp.row_order.tolist(), strict=True))
    slack = _elastic_slack(qp.G, qp.lo, qp.hi, keys, sorted(set(keys)))
    return sorted({g[0] for g, v in slack.items() if v > 1e-9})
