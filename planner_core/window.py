"""The iterative pass's hot path: one receding-window jet QP per waypoint, with few numpy calls.

Same QP as `jets.solve_jets(..., open_end=True)` with the dense backend (same
rows, same tightening, same cost, same exactness check); what differs is how
it is put together:

- every segment's hull rows are stacked once per problem into global arrays
  with columns already scaled per jet, so a window's rows are one contiguous
  slice `[r0, r1)` of them (roles 'b' | 'ab'... | 'half' are contiguous by the
  [start only | both | end only] row order of `SegBlocks`);
- the cost Hessian blocks (free part of each segment, 24 x 24) and the
  position part of the gradient are precomputed for all segments;
- daqp's setup costs ~rows x n^2, so only a working set of rows goes to the
  solver: the rows active at the previous window plus those violated at the
  guess; all rows are checked with one matmul and violated ones added
  (a solution of the relaxation that is feasible for every row is optimal for
  the full QP).

A solve returns None when the QP is infeasible or the check fails; the
caller then falls back to the general path (`solve_jets`), which also runs
recovery and diagnosis.
"""

from __future__ import annotations

from time import perf_counter

import numpy as np
from numpy.typing import NDArray

from planner_core.jets import CHECK_TOL, NV, ProblemCache

FloatArray = NDArray[np.float64]

MAX_ROUNDS = 8  # working-set growth rounds before giving up on the fast path
ADD_TOL = 1e-12  # relative: a row outside its tightened limit by more joins the working set
_ORD = np.repeat(np.arange(1, 5), 3).astype(float)


def jet_scales(durations: FloatArray) -> FloatArray:
    """(m, 12) column scale τ^-k of each jet's derivatives (τ: mean adjacent duration); 1 at the ends.

    Without it long segments give Hessians with condition numbers ~ Δ^8.
    """
    d = np.asarray(durations, dtype=float)
    out = np.ones((d.size + 1, NV))
    tau = 0.5 * (d[:-1] + d[1:])
    out[1:-1] = tau[:, None] ** -_ORD[None, :]
    return out


class WindowSolver:
    """Stacked, pre-scaled rows and cost blocks of one problem (built once, O(m))."""

    def __init__(self, cache: ProblemCache, cost_order: int = 4) -> None:
        import daqp

        self._daqp_solve = daqp.solve
        problem = cache.problem
        self.problem = problem
        self.cache = cache
        m = problem.m
        n_seg = m - 1
        blocks = [cache.blocks(s) for s in range(n_seg)]
        sizes = np.array([b.kind.size for b in blocks], dtype=np.int64)
        self.off = np.concatenate([[0], np.cumsum(sizes)]).tolist()
        self.n1 = [b.n1 for b in blocks]
        self.n2 = [b.n2 for b in blocks]
        cs = jet_scales(cache.durations)
        self.cs = cs
        seg_of_row = np.repeat(np.arange(n_seg), sizes)
        ab = np.empty((int(sizes.sum()), 2 * NV))
        ab[:, :NV] = np.concatenate([b.A for b in blocks])
        ab[:, NV:] = np.concatenate([b.B for b in blocks])
        ab[:, :NV] *= cs[seg_of_row]
        ab[:, NV:] *= cs[seg_of_row + 1]
        self.ab = ab
        self.c0 = np.concatenate([b.c0 for b in blocks])
        self.lim = np.concatenate([b.lim for b in blocks], axis=1)  # (4, R): lo_t, hi_t, lo, hi
        self.active = np.zeros(ab.shape[0], dtype=bool)  # rows active at the last solution
        self.sense = np.zeros(ab.shape[0], dtype=np.int32)
        self.times = (0.0, 0.0, 0.0)  # build, backend, check of the last successful solve (s)
        self.rows_used = 0
        # cost: free part [start derivatives | end derivatives] of each segment, scaled
        k30 = cache.cost30(cost_order)
        fi = np.r_[3:15, 18:30]
        c24 = np.concatenate([cs[:-1], cs[1:]], axis=1)  # (S, 24)
        self.k24 = k30[:, fi][:, :, fi] * c24[:, :, None] * c24[:, None, :]
        w = problem.waypoints
        zpos = np.concatenate([w[:-1], w[1:]], axis=1)  # (S, 6)
        self.qpos = np.einsum("sij,sj->si", k30[:, fi][:, :, [0, 1, 2, 15, 16, 17]], zpos) * c24
        # gradient from a fixed neighbour's derivatives (unscaled columns: they multiply jets)
        self.k_ba = k30[:, 18:30, 3:15] * cs[1:, :, None]  # end-jet rows x start-jet derivatives
        self.k_ab = k30[:, 3:15, 18:30] * cs[:-1, :, None]

    def solve(self, jets: FloatArray, f0: int, f1: int, open_end: bool, guess: FloatArray) -> FloatArray | None:
        """Derivatives (f1-f0+1, 4, 3) of jets f0..f1 given the others in `jets`, or None.

        `guess` (m, 5, 3) seeds the working set; it need not be feasible.
        """
        t_start = perf_counter()
        m = self.problem.m
        nf = f1 - f0 + 1
        nx = NV * nf
        off, n1, n2 = self.off, self.n1, self.n2
        sb = f0 - 1
        half = open_end and f1 < m - 2
        r0 = off[sb] + n1[sb]
        r1 = off[f1] + n1[f1] + (0 if half else n2[f1])
        nr = r1 - r0
        ab = self.ab
        cs = self.cs
        # --- rows: G in scaled columns, constants from the fixed neighbours ---
        G = np.zeros((nr, nx))
        kb = off[f0] - r0
        G[:kb, :NV] = ab[r0 : off[f0], NV:]
        for i in range(nf - 1):
            s = f0 + i
            G[off[s] - r0 : off[s + 1] - r0, NV * i : NV * i + 2 * NV] = ab[off[s] : off[s + 1]]
        G[off[f1] - r0 :, nx - NV :] = ab[off[f1] : r1, :NV]
        const = self.c0[r0:r1].copy()
        const[:kb] += ab[r0 : off[f0], :NV] @ (jets[sb, 1:].ravel() / cs[sb])
        if f0 == 1 and not self._constants_hold(sb, jets[sb, 1:].ravel() / cs[sb], 0, n1[sb], side=0):
            return None
        if not half:
            end = jets[f1 + 1, 1:].ravel() / cs[f1 + 1]
            const[off[f1] - r0 :] += ab[off[f1] : r1, NV:] @ end
            if not self._constants_hold(f1, end, n1[f1] + n2[f1], off[f1 + 1] - off[f1], side=1):
                return None
        lims = self.lim[:, r0:r1] - const
        # --- cost ---
        H = np.zeros((nx, nx))
        q = np.zeros(nx)
        H[:NV, :NV] = self.k24[sb, NV:, NV:]
        q[:NV] = self.qpos[sb, NV:] + self.k_ba[sb] @ jets[sb, 1:].ravel()
        for i in range(nf - 1):
            s = f0 + i
            H[NV * i : NV * i + 2 * NV, NV * i : NV * i + 2 * NV] += self.k24[s]
            q[NV * i : NV * i + 2 * NV] += self.qpos[s]
        if not half:
            H[nx - NV :, nx - NV :] += self.k24[f1, :NV, :NV]
            q[nx - NV :] += self.qpos[f1, :NV] + self.k_ab[f1] @ jets[f1 + 1, 1:].ravel()
        pscale = float(H.diagonal().max()) or 1.0
        H /= pscale
        q /= pscale
        t_built = perf_counter()
        t_solve = 0.0
        # --- working set: previous active rows plus rows violated at the guess ---
        c = cs[f0 : f1 + 1].ravel()
        r = G @ (guess[f0 : f1 + 1, 1:].ravel() / c)
        lo_t, hi_t = lims[0], lims[1]
        work = self.active[r0:r1] | (r > hi_t) | (r < lo_t)
        tol = ADD_TOL * (1.0 + np.abs(lims[:2]))
        for _ in range(MAX_ROUNDS):
            idx = np.flatnonzero(work)
            gw = G[idx]
            nrm = np.sqrt(np.einsum("ij,ij->i", gw, gw))
            nrm[nrm == 0.0] = 1.0
            gw /= nrm[:, None]
            hw = hi_t[idx] / nrm
            lw = lo_t[idx] / nrm
            ts = perf_counter()
            x, _, flag, info = self._daqp_solve(
                H, q, gw, hw, lw, self.sense[: idx.size], primal_tol=1e-10, iter_limit=2000
            )
            t_solve += perf_counter() - ts
            if flag != 1 and flag != 2:
                return None
            r = G @ x
            bad = (r > hi_t + tol[1]) | (r < lo_t - tol[0])
            if not bad.any():
                viol = max(float(np.max(r - lims[3])), float(np.max(lims[2] - r)))
                if viol > CHECK_TOL:
                    return None
                act = self.active[r0:r1]
                act[:] = False
                act[idx[np.asarray(info["lam"]) != 0.0]] = True
                t_end = perf_counter()
                self.times = (t_built - t_start, t_solve, t_end - t_built - t_solve)
                self.rows_used = int(idx.size)
                return np.asarray((x * c).reshape(nf, 4, 3))
            work |= bad
        return None

    def _constants_hold(self, s: int, fixed: FloatArray, a: int, b: int, side: int) -> bool:
        """Rows [a, b) of segment s depend only on one fixed jet (and positions): they must hold."""
        lo, hi = self.off[s] + a, self.off[s] + b
        if hi <= lo:
            return True
        cols = slice(0, NV) if side == 0 else slice(NV, 2 * NV)
        v = self.c0[lo:hi] + self.ab[lo:hi, cols] @ fixed
        return bool(np.all(v <= self.lim[3, lo:hi] + CHECK_TOL) and np.all(v >= self.lim[2, lo:hi] - CHECK_TOL))
