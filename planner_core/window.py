"""The iterative pass's hot path: one receding-window jet QP per waypoint, with few numpy calls.

Same QP as `jets.solve_jets(..., open_end=True)` with the dense backend (same
rows, same tightening, same cost); what differs is how it is put together:

- the hull rows of the segments near the window are stacked (columns already
  scaled per jet) in a store that slides along with it, `CHUNK` segments at a
  time, so a window's rows are one contiguous slice of it (roles
  'b' | 'ab'... | 'half' are contiguous by the [start only | both | end only]
  row order of `SegBlocks`); the rows of the whole mission are never held at
  once (~70 MB at m = 1000: most of a planner process's peak);
- the cost Hessian blocks (free part of each segment, per axis: 8 x 8) and the
  position part of the gradient are precomputed for all segments;
- daqp factors H and forms G R^-1 in plain C at every call (~100 us at 48
  unknowns, measured); here LAPACK factors H = L L' and daqp gets the
  equivalent problem in u = L'x with H = I (~10x cheaper setup);
- only a working set of rows goes to the solver: the rows active at the
  previous window plus every row of the open-end segment (the last jet is
  pushed against them: the cost does not see that segment); all rows are then
  checked with one matmul and violated ones added (a solution of the
  relaxation that is feasible for every row is optimal for the full QP).
  Measured: one round in >90% of steps.

A solve returns None when the QP is infeasible or anything does not check;
the caller then falls back to the general path (`solve_jets`), which also
runs recovery and diagnosis. Nothing is returned that failed the check
against the tightened rows (which implies the untightened ones).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache
from time import perf_counter
from types import ModuleType

import numpy as np
from numpy.typing import NDArray

from planner_core.constraints import INF, cost_matrices
from planner_core.jets import CHECK_TOL, MARGIN, NV, ProblemCache, tighten
from planner_core.kernel_aot import AotKernel
from planner_core.qp import DaqpSolver

FloatArray = NDArray[np.float64]

CHUNK = 32  # segments of rows the window solver holds: filled in one vectorised block as it reaches them
MAX_ROUNDS = 8  # working-set growth rounds before giving up on the fast path
ADD_TOL = 1e-12  # relative: a row outside its tightened limit by more joins the working set
_ORD = np.repeat(np.arange(1, 5), 3).astype(float)


_kernel_off: list[str] = []  # set by use_compiled_kernel(False): this process never loads numba


def use_compiled_kernel(enabled: bool, reason: str = "disabled by the caller") -> str | None:
    """Process-wide: allow the compiled pass (the default; `kernel_build`: which build) or, with
    `enabled=False`, plan without it and never import numba (~105 MB resident; loading it from its
    cache ~0.4 s) nor load the AOT build: the companion's processes, a one-shot CLI plan of a
    small problem. Per plan, the same choice is `IterativeOptions.compiled`. Returns the reason it
    was off before (None: it was on), so a caller that borrows the switch (a replay) can put it
    back."""
    before = _kernel_off[0] if _kernel_off else None
    if enabled:
        _kernel_off.clear()
    else:
        _kernel_off[:] = [reason]
    return before


BUILDS = ("auto", "aot", "jit")
# which build of the compiled pass a process loads: `kernel_build`, or PLANNER_CORE_KERNEL (a
# value not in BUILDS: auto)
_build: list[str] = [b if (b := os.environ.get("PLANNER_CORE_KERNEL", "auto")) in BUILDS else "auto"]
_aot_reason: list[str] = []  # why the AOT build is not the one loaded (when it is not)


def kernel_build(build: str) -> str:
    """Process-wide: which build of the compiled pass to load. `auto` (the default): the
    ahead-of-time build (`python -m planner_core.build_kernel`: a plain extension module, no
    numba, ~ms to load) when it is there and built from the kernel's sources as they are, else numba's
    JIT (`window_kernel`); `aot`: that build only (else no compiled pass, with the reason);
    `jit`: numba's only. The environment variable PLANNER_CORE_KERNEL sets it at start-up.
    `use_compiled_kernel(False)` still means no compiled pass at all. Returns the build before."""
    if build not in BUILDS:
        raise ValueError(f"kernel build {build!r}: one of {', '.join(BUILDS)}")
    before = _build[0]
    _build[0] = build
    _load_kernel.cache_clear()
    return before


def _kernel_or_reason() -> ModuleType | AotKernel | str:
    """The compiled pass (`window_kernel`, or its AOT build), or why it is not used here. numba
    needs memory it can make executable; a W^X policy (systemd's MemoryDenyWriteExecute=yes,
    SELinux execmem) refuses it at import. Without it every window takes the numpy + daqp
    path: same QPs, same checks, ~8x slower."""
    if _kernel_off:
        return _kernel_off[0]
    return _load_kernel()


@lru_cache(maxsize=1)
def _load_kernel() -> ModuleType | AotKernel | str:
    build = _build[0]
    _aot_reason.clear()
    if build in ("auto", "aot"):
        from planner_core import kernel_aot

        aot = kernel_aot.load()
        if not isinstance(aot, str):
            return aot
        if build == "aot":
            return f"AOT build: {aot} (kernel build 'aot': no JIT)"
        _aot_reason.append(aot)
    else:
        _aot_reason.append(f"not wanted (kernel build {build!r})")
    try:
        from planner_core import window_kernel
    except (ImportError, OSError) as exc:
        return f"{type(exc).__name__}: {exc}"
    return window_kernel


def kernel_kind() -> str | None:
    """`aot` or `jit`: the build of the compiled pass this process uses (loading it), None when none."""
    k = _kernel_or_reason()
    if isinstance(k, str):
        return None
    return "aot" if isinstance(k, AotKernel) else "jit"


def aot_ready() -> bool:
    """Whether the AOT build loads in this process (cheap: ~ms, no numba), without loading the JIT."""
    if _kernel_off or _build[0] == "jit":
        return False
    from planner_core import kernel_aot

    return not isinstance(kernel_aot.load(), str)


def aot_unavailable() -> str | None:
    """Why the AOT build of the compiled pass is not the one this process uses (not built, built
    from another source, not wanted, ...), None when it is. Loads the compiled pass."""
    if _kernel_off:
        return _kernel_off[0]
    k = _load_kernel()
    if isinstance(k, AotKernel):
        return None
    return _aot_reason[0] if _aot_reason else k if isinstance(k, str) else None


def kernel_unavailable() -> str | None:
    """None when the compiled pass runs here, else the reason it does not."""
    k = _kernel_or_reason()
    return k if isinstance(k, str) else None


def _kron3(a: FloatArray) -> FloatArray:
    """(S, p, q) -> (S, 3p, 3q): kron(a[s], I3), index i*3 + axis (the jets' layout)."""
    n, p, q = a.shape
    out = np.zeros((n, p, 3, q, 3))
    for d in range(3):
        out[:, :, d, :, d] = a
    return out.reshape(n, 3 * p, 3 * q)


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
    """Pre-scaled rows near the window and cost blocks of one problem.

    Rows are built `CHUNK` segments at a time as the window reaches them (each
    segment once on a forward pass, as when the whole mission's rows were kept),
    and dropped once the window has passed them: a solver rebuilt after a
    duration stretch only pays for the segments it still visits, and memory
    does not grow with m (except the working-set flags, one byte a row).
    """

    def __init__(self, cache: ProblemCache, cost_order: int = 4) -> None:
        self._dense = DaqpSolver(primal_tol=1e-10, iter_limit=2000)
        problem = cache.problem
        self.problem = problem
        self.cache = cache
        cs = jet_scales(cache.durations)
        self.cs = cs
        self._rows = _RowStore(cache, cs, span=CHUNK, working=True)
        self.off, self.n1, self.n2 = self._rows.off, self._rows.n1, self._rows.n2
        # rows active at the last solution, over the whole mission: the compiled pass keeps it too
        self.active = np.zeros(self._rows.n_rows, dtype=bool)
        self.sense = np.zeros(0, dtype=np.int32)
        self._eyes: dict[int, FloatArray] = {}
        self.times = (0.0, 0.0, 0.0)  # build, backend, check of the last successful solve (s)
        self.rows_used = 0
        # cost: free part [start derivatives | end derivatives] of each segment, scaled; per axis
        # (10 x 10): the same cost for each of the 3
        k10 = 2.0 * cost_matrices(cache.durations, cost_order)  # (S, 10, 10), Hessian of z'Kz
        free = np.r_[1:5, 6:10]
        # column scales are the same on every axis (jet_scales): the 8 x 8 per-axis blocks are
        # scaled here and spread over the axes per window (all segments' would be ~6 MB at m = 1000)
        c8 = np.concatenate([cs[:-1, ::3], cs[1:, ::3]], axis=1)  # (S, 8)
        k8 = k10[:, free][:, :, free] * c8[:, :, None] * c8[:, None, :]
        self.k8 = k8  # per axis: both passes work on H4, with H = H4 (x) I3
        w = problem.waypoints
        # position part of the gradient: K[free, 0] p0 + K[free, 5] p1, per axis
        gpos = k10[:, free, 0, None] * w[:-1, None, :] + k10[:, free, 5, None] * w[1:, None, :]
        self.qpos = (gpos * c8[:, :, None]).reshape(-1, 2 * NV)
        # gradient from a fixed neighbour's derivatives (unscaled columns: they multiply jets), per
        # axis: end-jet rows x start-jet derivatives, and the reverse
        self.kba4 = np.ascontiguousarray(k10[:, 6:10, 1:5] * c8[:, 4:, None])
        self.kab4 = np.ascontiguousarray(k10[:, 1:5, 6:10] * c8[:, :4, None])
        # per-waypoint Hessian/gradient sums of the two segments meeting there (index 0 and m-1 unused)
        self.kdd = np.zeros((problem.m, 4, 4))  # per axis
        self.kdd[1:-1] = k8[:-1, 4:, 4:] + k8[1:, :4, :4]
        self.qsum = np.zeros((problem.m, NV))
        self.qsum[1:-1] = self.qpos[:-1, NV:] + self.qpos[1:, :NV]
        self._idx: _CompactRows | None = None

    def solve(self, jets: FloatArray, f0: int, f1: int, open_end: bool) -> FloatArray | None:
        """Derivatives (f1-f0+1, 4, 3) of jets f0..f1 given the others in `jets`, or None."""
        t_start = perf_counter()
        m = self.problem.m
        nf = f1 - f0 + 1
        nx = NV * nf
        off, n1, n2 = self.off, self.n1, self.n2
        sb = f0 - 1
        store = self._rows
        row0 = store.hold(sb, f1)  # the store's first row: rows below are indices into the mission's
        half = open_end and f1 < m - 2
        r0 = off[sb] + n1[sb]
        r1 = off[f1] + n1[f1] + (0 if half else n2[f1])
        nr = r1 - r0
        ab = store.ab[r0 - row0 : r1 - row0]  # the window's rows: index r - r0 is mission row r
        cs = self.cs
        # --- rows: G in scaled columns, constants from the fixed neighbours ---
        G = np.zeros((nr, nx))
        kb = off[f0] - r0
        G[:kb, :NV] = ab[:kb, NV:]
        for i in range(nf - 1):
            s = f0 + i
            G[off[s] - r0 : off[s + 1] - r0, NV * i : NV * i + 2 * NV] = ab[off[s] - r0 : off[s + 1] - r0]
        ke = off[f1] - r0
        G[ke:, nx - NV :] = ab[ke:, :NV]
        # (4, nr): limits less the fixed positions' part
        lims = store.limw[:, r0 - row0 : r1 - row0] - store.c0[r0 - row0 : r1 - row0]
        start = jets[sb, 1:].ravel() / cs[sb]
        lims[:, :kb] -= ab[:kb, :NV] @ start
        if f0 == 1 and not self._constants_hold(sb, start, 0, n1[sb], side=0):
            return None
        if not half:
            end = jets[f1 + 1, 1:].ravel() / cs[f1 + 1]
            lims[:, ke:] -= ab[ke:, NV:] @ end
            if not self._constants_hold(f1, end, n1[f1] + n2[f1], off[f1 + 1] - off[f1], side=1):
                return None
        # --- cost: assembled per axis (the same on each), then spread over the axes ---
        k8 = self.k8
        n4 = 4 * nf
        h4 = np.zeros((n4, n4))
        q = np.zeros(nx)
        h4[:4, :4] = k8[sb, 4:, 4:]
        q[:NV] = self.qpos[sb, NV:] + (self.kba4[sb] @ jets[sb, 1:]).ravel()
        for i in range(nf - 1):
            s = f0 + i
            h4[4 * i : 4 * i + 8, 4 * i : 4 * i + 8] += k8[s]
            q[NV * i : NV * i + 2 * NV] += self.qpos[s]
        if not half:
            h4[n4 - 4 :, n4 - 4 :] += k8[f1, :4, :4]
            q[nx - NV :] += self.qpos[f1, :NV] + (self.kab4[f1] @ jets[f1 + 1, 1:]).ravel()
        H = _kron3(h4[None])[0]
        # daqp factors H and forms G R^-1 in plain C at every call (~100 us at 48 unknowns);
        # doing it with LAPACK here and handing daqp H = I costs a fraction of that
        # (numpy's LAPACK, not scipy's: importing scipy.linalg costs ~0.1 s of a one-shot plan)
        try:
            chol = np.linalg.cholesky(H)
        except np.linalg.LinAlgError:
            return None
        li = np.linalg.inv(chol)  # L^-1: x = L^-T u, u'u/2 + (L^-1 q)'u, rows G L^-T
        f = li @ q
        lt = li.T
        t_built = perf_counter()
        t_solve = 0.0
        c = cs[f0 : f1 + 1].ravel()
        # working set: rows active at the previous window and the open end's rows (the last jet
        # is pushed against them: the cost does not see that segment); measured: one round in
        # >90% of steps, where seeding from the previous window's solution did no better
        work = self.active[r0:r1].copy()
        if half:
            work[off[f1] - r0 :] = True
        lo_x, hi_x = lims[2], lims[3]
        eye = self._eye(nx)
        if self.sense.size < nr:
            self.sense = np.zeros(nr, dtype=np.int32)
        for _ in range(MAX_ROUNDS):
            idx = np.flatnonzero(work)
            gw = G[idx] @ lt
            nrm = np.maximum(np.sqrt(np.einsum("ij,ij->i", gw, gw)), 1e-300)
            gw /= nrm[:, None]
            # daqp reads its arrays' buffers as C-contiguous: lims[:2, idx] would be F-ordered
            hw = lims[1, idx] / nrm
            lw = lims[0, idx] / nrm
            ts = perf_counter()
            sol = self._dense.solve(eye, f, gw, hw, lw, self.sense[: idx.size])
            t_solve += perf_counter() - ts
            if not sol.ok:
                return None
            x = lt @ sol.x
            r = G @ x
            # hi_x < hi - 1e-6 (1 + |hi|): passing this check passes the untightened rows
            bad = (r > hi_x) | (r < lo_x)
            if not bad.any():
                act = self.active[r0:r1]
                act[:] = False
                act[idx[sol.lam != 0.0]] = True
                self.times = (t_built - t_start, t_solve, perf_counter() - t_built - t_solve)
                self.rows_used = int(idx.size)
                return np.asarray((x * c).reshape(nf, 4, 3))
            bad &= ~work
            if not bad.any():
                return None  # a working row missed by more than rounding: let the general path decide
            work |= bad
        return None

    def run(self, jets: FloatArray, guess: FloatArray, j0: int, window: int, step_times: FloatArray) -> int:
        """Compiled pass (`window_kernel.run_pass`) from waypoint j0: commits jets in place, writes
        each window's solution to `guess` and each step's seconds to `step_times[j]`; returns the
        first waypoint it could not settle (m-1 when none)."""
        kernel = _kernel_or_reason()
        if isinstance(kernel, str):
            return j0
        m = self.problem.m
        c = self._compact()
        return int(
            kernel.run_pass(
                j0, window, m, c.off, c.n1, c.n2, self.cache.hull, self.cs, c.pr, c.pd, c.bn1, c.nb,
                c.face_off, c.pa, self.problem.waypoints, c.b6, c.f6,
                self.k8, self.kdd, self.qpos, self.qsum, self.kba4, self.kab4, jets, guess, self.active,
                step_times, CHECK_TOL, np.zeros(2, dtype=np.int64),
            )
        )

    def _compact(self) -> _CompactRows:
        if self._idx is None:
            self._idx = _compact_rows(self._rows)
        return self._idx

    def _eye(self, n: int) -> FloatArray:
        eye = self._eyes.get(n)
        if eye is None:
            eye = self._eyes[n] = np.eye(n)
        return eye

    def _seed_new_rows(self, work: NDArray[np.bool_], r0: int, f1: int) -> None:
        """Rows new to this window (the half segment f1, the rest of segment f1-1) take the
        active pattern of the same rows one segment earlier: the window slides, the shape of
        the solution near its open end repeats."""
        off, n1 = self.off, self.n1
        a, b = f1 - 1, f1
        if n1[a] == n1[b]:
            work[off[b] - r0 : off[b] - r0 + n1[b]] |= self.active[off[a] : off[a] + n1[a]]
        if f1 >= 2 and off[b] - off[a] == off[a] - off[a - 1] and n1[a] == n1[a - 1]:
            lo = off[a] + n1[a]
            work[lo - r0 : off[b] - r0] |= self.active[off[a - 1] + n1[a - 1] : off[a]]

    def _constants_hold(self, s: int, fixed: FloatArray, a: int, b: int, side: int) -> bool:
        """Rows [a, b) of segment s (held by the store) depend only on one fixed jet (and
        positions): they must hold."""
        store = self._rows
        lo, hi = self.off[s] + a - store.row0, self.off[s] + b - store.row0
        if hi <= lo:
            return True
        cols = slice(0, NV) if side == 0 else slice(NV, 2 * NV)
        v = store.c0[lo:hi] + store.ab[lo:hi, cols] @ fixed
        return bool(np.all(v <= store.lim[3, lo:hi] + CHECK_TOL) and np.all(v >= store.lim[2, lo:hi] - CHECK_TOL))


def stack_rows(
    cache: ProblemCache, cs: FloatArray
) -> tuple[list[int], list[int], list[int], FloatArray, FloatArray, FloatArray]:
    """All segments' rows in `SegBlocks` order, stacked: offsets per segment, n1, n2 per
    segment, [A | B] (R, 24) with columns scaled by `cs`, c0 (R,), limits (4, R)."""
    store = _RowStore(cache, cs)
    store.hold(0, len(store.n1) - 1)
    return store.off, store.n1, store.n2, store.ab, store.c0, store.lim


class _RowStore:
    """Stacked rows of a run of consecutive segments `[seg0, seg1)`, built on demand.

    Row r of the mission (`off` counts them) is row r - `row0` of the arrays. With
    `span` (segments), `hold` slides the run forward: the rows still wanted move to
    the front (a copy of a window's worth) and the next `span` or so segments are
    built; without it, the arrays have room for every segment's rows (the global QP).
    Segments are built in groups of equal corridor size (one dense (g, rows, 24)
    block each, then one row scatter): element-wise scatters were 5x slower.
    `working` adds the solver's working limits `limw`: tightened (for the solver),
    and tightened + ADD_TOL relative (to accept a row).
    """

    def __init__(self, cache: ProblemCache, cs: FloatArray, span: int | None = None, working: bool = False) -> None:
        problem = cache.problem
        self.cache = cache
        self.cs = cs
        n_seg = problem.m - 1
        self.polys = list(problem.corridors) if problem.corridors is not None else [None] * n_seg
        self.faces = np.array([0 if p is None else p.b.size for p in self.polys], dtype=np.int64)
        nb = cache.bound_spec.point.size
        off = np.concatenate([[0], np.cumsum(nb + 8 * self.faces)])
        n_rows = int(off[-1])
        self.n_rows = n_rows
        self._off = off
        self.off: list[int] = off.tolist()
        self.n1: list[int] = (cache.bound_spec.n_start + 4 * self.faces).tolist()
        self.n2: list[int] = [cache.bound_spec.n_both] * n_seg
        # corridors flattened: faces of segment s are rows face_off[s]:face_off[s+1] of pa, pb
        self._face_off = np.concatenate([[0], np.cumsum(self.faces)]).astype(np.int64)
        planes = [p for p in self.polys if p is not None and p.A.shape[0]]
        self._pa = np.concatenate([p.A for p in planes]) if planes else np.zeros((0, 3))
        self._pb = np.concatenate([p.b for p in planes]) if planes else np.zeros(0)
        self._blim = np.stack([cache.bound_spec.lo_t, cache.bound_spec.hi_t, cache.bound_spec.lo, cache.bound_spec.hi])
        self.span = n_seg if span is None else max(1, min(span, n_seg))
        self._working = working
        # room for the rows of any `span` consecutive segments
        first = np.arange(n_seg)
        cap = int(np.max(off[np.minimum(first + self.span, n_seg)] - off[first])) if n_seg else 0
        self._alloc(cap)
        self.seg0 = self.seg1 = self.row0 = 0

    def _alloc(self, n: int) -> None:
        self.ab = np.empty((n, 2 * NV))
        self.c0 = np.empty(n)
        self.lim = np.empty((4, n))
        self.limw = np.empty((4, n if self._working else 0))

    def hold(self, s0: int, s1: int) -> int:
        """Make segments s0..s1 (inclusive) held; returns `row0`, the mission row of array row 0."""
        if self.seg0 <= s0 and s1 < self.seg1:
            return self.row0
        off = self.off
        new0, new1 = s0, min(len(self.n1), max(s1 + 1, s0 + self.span))
        if off[new1] - off[new0] > self.c0.size:  # a window wider than the span: rare, start afresh
            self._alloc(off[new1] - off[new0])
            self.seg0 = self.seg1 = 0
        keep0, keep1 = max(new0, self.seg0), min(new1, self.seg1)
        if keep0 < keep1:
            # rows still wanted move to their new place (numpy copies overlapping slices safely)
            src, dst, n = off[keep0] - self.row0, off[keep0] - off[new0], off[keep1] - off[keep0]
            self.ab[dst : dst + n] = self.ab[src : src + n]
            self.c0[dst : dst + n] = self.c0[src : src + n]
            self.lim[:, dst : dst + n] = self.lim[:, src : src + n]
            if self._working:
                self.limw[:, dst : dst + n] = self.limw[:, src : src + n]
        else:
            keep0 = keep1 = new0
        self.seg0, self.seg1, self.row0 = new0, new1, off[new0]
        todo = np.r_[np.arange(new0, keep0), np.arange(keep1, new1)].astype(np.int64)
        if todo.size:
            self.fill(todo)
        return self.row0

    def fill(self, segments: NDArray[np.int64]) -> None:
        """Rows of `segments` (held: within [seg0, seg1)), and their working limits when the store
        keeps them. Compiled (`window_kernel.fill_rows`, JIT or AOT) where it runs, numpy otherwise."""
        cache = self.cache
        kernel = _kernel_or_reason()
        if isinstance(kernel, str):
            faces = self.faces[segments]
            for f in np.unique(faces).tolist():
                self._fill_group(segments[faces == f], int(f))
            if self._working:
                rows = np.concatenate(
                    [np.arange(self._off[s], self._off[s + 1]) for s in segments.tolist()]
                ) - self.row0
                lo_t, hi_t = self.lim[0, rows], self.lim[1, rows]
                self.limw[0, rows] = lo_t
                self.limw[1, rows] = hi_t
                self.limw[2, rows] = lo_t - ADD_TOL * (1.0 + np.abs(lo_t))
                self.limw[3, rows] = hi_t + ADD_TOL * (1.0 + np.abs(hi_t))
            return
        # fill_rows writes segment s at off[s]: offsets shifted to the store's first row; it skips
        # the working limits when limw has no columns (the global QP's store)
        kernel.fill_rows(
            segments, self._off - self.row0, cache.hull, cache.problem.waypoints, self.cs, cache.bound_spec.point,
            cache.bound_spec.code, cache.bound_spec.direction, int(cache.bound_spec.n_start), self._blim, self._face_off, self._pa, self._pb, INF, MARGIN, self.ab, self.c0, self.lim,
            self.limw, ADD_TOL,
        )

    def _fill_group(self, segs: NDArray[np.int64], f: int) -> None:
        cache, cs = self.cache, self.cs
        nb = cache.bound_spec.point.size
        bn1 = cache.bound_spec.n_start
        w = cache.problem.waypoints
        g = segs.size
        nrow = nb + 8 * f
        hull = cache.hull_of(segs)  # (g, 10 + n, 10): indexed by position in segs below
        # bound rows: [a-only | (corridor P1..P4) | both | end-only | (corridor P5..P8)]
        pos = np.arange(nb)
        bpos = pos + 4 * f * (pos >= bn1)
        blk = np.zeros((g, nrow, 2 * NV))
        cblk = np.empty((g, nrow))
        lblk = np.empty((4, g, nrow))
        dirs = cache.bound_spec.direction  # (nb, 3) the direction of each bound row: an axis or a horizontal one
        qb = hull[:, 10:][:, cache.bound_spec.point]  # (g, nb, 10) the certified hodograph point of each row
        ra = (qb[:, :, 1:5, None] * dirs[None, :, None, :]).reshape(g, nb, NV)
        rb = (qb[:, :, 6:10, None] * dirs[None, :, None, :]).reshape(g, nb, NV)
        blk[:, bpos, :NV] = ra * cs[segs, None, :]
        blk[:, bpos, NV:] = rb * cs[segs + 1, None, :]
        # direction . waypoint: exactly the coordinate for an axis row (products with 0 and 1)
        cb0 = qb[:, :, 0] * (w[segs] @ dirs.T) + qb[:, :, 5] * (w[segs + 1] @ dirs.T)
        cblk[:, bpos] = cb0
        blim = np.stack([cache.bound_spec.lo_t, cache.bound_spec.hi_t, cache.bound_spec.lo, cache.bound_spec.hi])  # (4, nb)
        lblk[:, :, bpos] = blim[:, None, :]
        if f:
            polys = [self.polys[s] for s in segs.tolist()]
            pa = np.stack([p.A for p in polys if p is not None])  # (g, f, 3)
            pb = np.stack([p.b for p in polys if p is not None])
            q = hull
            ka = slice(bn1, bn1 + 4 * f)
            kb = slice(nb + 4 * f, nrow)
            ca = (q[:, 1:5, None, 1:5, None] * pa[:, None, :, None, :]).reshape(g, 4 * f, NV)
            cb = (q[:, 5:9, None, 6:10, None] * pa[:, None, :, None, :]).reshape(g, 4 * f, NV)
            blk[:, ka, :NV] = ca * cs[segs, None, :]
            blk[:, kb, NV:] = cb * cs[segs + 1, None, :]
            cblk[:, ka] = (q[:, 1:5, 0, None] * np.einsum("gfd,gd->gf", pa, w[segs])[:, None, :]).reshape(g, -1)
            cblk[:, kb] = (q[:, 5:9, 5, None] * np.einsum("gfd,gd->gf", pa, w[segs + 1])[:, None, :]).reshape(g, -1)
            hi = np.clip(np.broadcast_to(pb[:, None, :], (g, 4, f)).reshape(g, 4 * f), -INF, INF)
            hi_t = tighten(np.full(hi.shape, -INF), hi)[1]
            for k in (ka, kb):
                lblk[0, :, k] = -INF
                lblk[1, :, k] = hi_t
                lblk[2, :, k] = -INF
                lblk[3, :, k] = hi
        rows = (self._off[segs, None] - self.row0 + np.arange(nrow)[None, :]).ravel()
        self.ab[rows] = blk.reshape(-1, 2 * NV)
        self.c0[rows] = cblk.ravel()
        self.lim[:, rows] = lblk.reshape(4, -1)




@dataclass(frozen=True)
class _CompactRows:
    """What the compiled pass builds rows from (see `window_kernel.run_pass`)."""

    off: NDArray[np.int64]
    n1: NDArray[np.int64]
    n2: NDArray[np.int64]
    pr: NDArray[np.int64]  # certified hodograph point of each bound row, in stacking order
    pd: NDArray[np.int64]  # its axis (3: a horizontal norm's polygon direction, b6[6:8])
    bn1: int
    nb: int
    face_off: NDArray[np.int64]
    pa: FloatArray
    b6: FloatArray  # (8, nb) per bound row: lo_t, hi_t, lo, hi, lo_w, hi_w, direction x, y
    f6: FloatArray  # (6, faces) the same per corridor face (lower limits -INF)


def _widen(lo_t: FloatArray, hi_t: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Tightened limits widened by ADD_TOL: a row outside these joins the working set."""
    return lo_t - ADD_TOL * (1.0 + np.abs(lo_t)), hi_t + ADD_TOL * (1.0 + np.abs(hi_t))


def _compact_rows(store: _RowStore) -> _CompactRows:
    cache = store.cache
    blo_t, bhi_t = cache.bound_spec.lo_t, cache.bound_spec.hi_t
    b6 = np.stack([blo_t, bhi_t, cache.bound_spec.lo, cache.bound_spec.hi, *_widen(blo_t, bhi_t), cache.bound_spec.direction[:, 0], cache.bound_spec.direction[:, 1]])
    hi = np.clip(store._pb, -INF, INF)
    lo = np.full(hi.shape, -INF)
    lo_t, hi_t = tighten(lo, hi)
    f6 = np.stack([lo_t, hi_t, lo, hi, *_widen(lo_t, hi_t)])
    return _CompactRows(
        np.asarray(store.off, dtype=np.int64), np.asarray(store.n1, dtype=np.int64),
        np.asarray(store.n2, dtype=np.int64), cache.bound_spec.point.astype(np.int64), cache.bound_spec.code.astype(np.int64),
        int(cache.bound_spec.n_start), int(cache.bound_spec.point.size), store._face_off, np.ascontiguousarray(store._pa, dtype=float), b6, f6,
    )
