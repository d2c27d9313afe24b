"""planner_core.qp: one typed entry (`solve_qp`) over every backend module, and the reusable
handles the hot loops keep (`DaqpSolver`, `OsqpSolver`), checked against each other."""

from __future__ import annotations

import numpy as np
import pytest

from planner_core.qp import (
    BACKENDS,
    INF,
    DaqpSolver,
    OsqpSolver,
    QPStatus,
    solve_lp,
    solve_qp,
)


def _small_qp() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(7)
    m = rng.normal(size=(6, 6))
    P = m @ m.T + 6.0 * np.eye(6)
    q = 20.0 * rng.normal(size=6)  # the unconstrained optimum is outside: some rows are active
    G = rng.normal(size=(9, 6))
    lo = np.full(9, -INF)
    hi = np.full(9, 0.2)
    return P, q, G, lo, hi


@pytest.mark.parametrize("backend", BACKENDS)
def test_every_backend_answers_the_same_qp(backend: str) -> None:
    P, q, G, lo, hi = _small_qp()
    ref = solve_qp(P, q, G, lo, hi, "daqp")
    res = solve_qp(P, q, G, lo, hi, backend)
    assert res.status is QPStatus.OPTIMAL and res.ok and res.backend == backend
    assert res.x is not None and ref.x is not None
    assert np.allclose(res.x, ref.x, atol=1e-8)


def test_an_infeasible_qp_has_the_infeasible_status_and_no_point() -> None:
    P = np.eye(1)
    G = np.array([[1.0], [1.0]])
    for backend in BACKENDS:
        res = solve_qp(P, np.zeros(1), G, np.array([1.0, -INF]), np.array([INF, -1.0]), backend)
        assert res.status is QPStatus.INFEASIBLE and res.x is None and not res.ok


def test_an_unknown_backend_is_named() -> None:
    P, q, G, lo, hi = _small_qp()
    with pytest.raises(ValueError, match=r"backend: unknown QP backend 'nope' \(expected one of \('daqp', 'osqp'\)\)"):
        solve_qp(P, q, G, lo, hi, "nope")


def test_the_daqp_handle_is_daqp_with_its_settings() -> None:
    P, q, G, lo, hi = _small_qp()
    sol = DaqpSolver(primal_tol=1e-10, iter_limit=2000).solve(P, q, G, hi, lo, np.zeros(9, dtype=np.int32))
    ref = solve_qp(P, q, G, lo, hi, "daqp")
    assert sol.ok and sol.exitflag in (1, 2) and ref.x is not None
    assert np.array_equal(sol.x, ref.x)  # the same call, bit for bit
    assert sol.lam.shape == (9,) and np.any(sol.lam != 0.0)  # some row active, its multiplier back


def test_the_osqp_workspace_is_set_up_once_and_updated() -> None:
    P, q, G, lo, hi = _small_qp()
    import scipy.sparse as sp

    lo_c = np.where(lo <= -INF, -np.inf, lo)
    solver = OsqpSolver()
    solver.setup(sp.triu(sp.csc_matrix(P), format="csc"), q, sp.csc_matrix(G), lo_c, hi,
                 verbose=False, eps_abs=1e-9, eps_rel=1e-9, max_iter=20000)
    first = solver.solve()
    ref = solve_qp(P, q, G, lo, hi, "daqp").x
    assert first.status is QPStatus.OPTIMAL and first.x is not None and first.y is not None and ref is not None
    assert np.allclose(first.x, ref, atol=1e-5)
    solver.update(q=-q)
    solver.warm_start(x=first.x)
    second = solver.solve()
    ref2 = solve_qp(P, -q, G, lo, hi, "daqp").x
    assert second.status is QPStatus.OPTIMAL and second.x is not None and ref2 is not None
    assert np.allclose(second.x, ref2, atol=1e-5)


def test_the_lp() -> None:
    # min -x - y s.t. x + y <= 1, x <= 0.75, y >= 0
    res = solve_lp(np.array([-1.0, -1.0]), np.array([[1.0, 1.0], [1.0, 0.0]]), np.array([1.0, 0.75]),
                   [(None, None), (0, None)])
    assert res.ok and res.status == 0 and res.x is not None
    assert float(res.x.sum()) == pytest.approx(1.0)
    bad = solve_lp(np.zeros(1), np.array([[1.0], [-1.0]]), np.array([-1.0, -1.0]), [(None, None)])
    assert not bad.ok and bad.status == 2
