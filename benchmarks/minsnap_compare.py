"""Side by side with `minsnap-trajectories` (PyPI), what a Python user would pick instead.

    pip install -e '.[bench]'     # minsnap-trajectories
    python benchmarks/minsnap_compare.py [--random 5] [--json PATH]

Same waypoints, same durations, same boundary jets (rest), same continuity
(C^4: `num_continuous_orders=5`), degree 9. minsnap-trajectories has two
solvers, "closed-form" (Bry & Roy's unconstrained reformulation) and
"constrained" (Mellinger & Kumar's QP through SLSQP); the second has only the
waypoint and continuity *equalities*: neither can take derivative limits or
corridors. Its piecewise power-basis polynomials (degree 9) are converted
exactly to our Bézier form (power -> Bernstein), so `verify` and the same hull
and dense-sample checks apply to both. Reported: time per plan, integrated
squared snap, and the worst violation of each derivative bound (sampled, i.e.
the real curve; and on the hull) and of the corridors.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from math import comb
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from quality import faster, random_scenario, snap_cost, table

from planner_core import IterativeOptions, Problem, Trajectory, verify
from planner_core.bezier import bernstein_basis, hodographs
from planner_core.formats.io import load_scenario
from planner_core.global_qp import plan_global
from planner_core.iterative import plan_iterative
from planner_core.problem import DEGREE

Row = dict[str, Any]
ROOT = Path(__file__).resolve().parents[1]
SAMPLES = 400  # per segment, for the sampled checks
CONSTRAINED_MAXITER = 1000
FAST_FACTOR = 0.65  # some random scenes are also flown this much faster: the bounds then matter
INSTALL_HINT = "minsnap-trajectories is not installed: pip install -e '.[bench]'"


def power_to_bezier(coeffs: np.ndarray, durations: np.ndarray) -> np.ndarray:
    """(s, n+1, 3) power coefficients in t - t_i (seconds) -> (s, n+1, 3) Bézier control points.

    With u = (t - t_i)/Δ the coefficients become a_j = c_j Δ^j, and
    P_k = Σ_{j<=k} C(k, j) / C(n, j) a_j (exact change of basis).
    """
    n = coeffs.shape[1] - 1
    a = coeffs * durations[:, None, None] ** np.arange(n + 1)[None, :, None]
    m = np.array([[comb(k, j) / comb(n, j) if j <= k else 0.0 for j in range(n + 1)] for k in range(n + 1)])
    return np.asarray(np.einsum("kj,sjd->skd", m, a))


def minsnap_plan(problem: Problem, algorithm: str, maxiter: int | None = None) -> tuple[Trajectory | None, float, str]:
    """Plan with minsnap-trajectories; (trajectory in our form or None, seconds, message).

    maxiter: SLSQP iteration limit for "constrained" (its default, 100, stops
    short on these problems with "Iteration limit reached").
    """
    opts = None if maxiter is None else {"options": {"maxiter": maxiter}}
    import minsnap_trajectories as ms

    init, fin = problem.initial, problem.final
    refs = []
    for i, (t, w) in enumerate(zip(problem.times, problem.waypoints, strict=True)):
        if i in (0, problem.m - 1):
            jet = init if i == 0 else fin
            refs.append(ms.Waypoint(time=float(t), position=w, velocity=jet[1], acceleration=jet[2],
                                    jerk=jet[3], snap=jet[4]))
        else:
            refs.append(ms.Waypoint(time=float(t), position=w))
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            poly = ms.generate_trajectory(refs, degree=DEGREE, idx_minimized_orders=4,
                                          num_continuous_orders=5, algorithm=algorithm,  # type: ignore[arg-type]
                                          optimize_options=opts)
    except (RuntimeError, ValueError) as exc:
        return None, time.perf_counter() - t0, str(exc)
    dt = time.perf_counter() - t0
    ctrl = power_to_bezier(np.asarray(poly.coefficients), np.asarray(poly.durations))
    return Trajectory(problem.times.copy(), ctrl, problem.corridors), dt, "planned"


def violations(traj: Trajectory, problem: Problem) -> Row:
    """Worst bound excess per order (hull and dense samples) and worst corridor excess (> 0 = violated)."""
    d = np.diff(traj.times)
    u = np.linspace(0.0, 1.0, SAMPLES)
    out: Row = {}
    for k, name in enumerate(("v", "a", "j", "s"), start=1):
        pts = hodographs(traj.control_points, k, d)
        lo, hi = problem.bounds.lo[k - 1], problem.bounds.hi[k - 1]
        out[f"{name}_hull"] = float(np.max(np.maximum(pts - hi, lo - pts)))
        vals = np.einsum("ti,sid->std", bernstein_basis(DEGREE - k, u), pts)
        out[f"{name}_viol"] = float(np.max(np.maximum(vals - hi, lo - vals)))
        # relative use of the bound on the real curve: 1.0 = at the limit
        out[f"{name}_use"] = float(np.max(np.maximum(vals / hi, vals / lo)))
    cor_hull, cor_samp = -np.inf, -np.inf
    basis = bernstein_basis(DEGREE, u)
    for s, poly in enumerate(problem.corridors or ()):
        if poly is None or poly.A.shape[0] == 0:
            continue
        cor_hull = max(cor_hull, poly.violation(traj.control_points[s]))
        cor_samp = max(cor_samp, poly.violation(basis @ traj.control_points[s]))
    hull = [out[f"{n}_hull"] for n in ("v", "a", "j", "s")]
    k = int(np.argmax(hull))
    out["bound_hull"] = f"{hull[k]:.3g} ({'vajs'[k]})"  # worst hodograph-hull excess, and its order
    out["corridor_hull"] = float(cor_hull)
    out["corridor_viol"] = float(cor_samp)
    return out


def _row(name: str, planner: str, traj: Trajectory | None, dt: float, msg: str, problem: Problem,
         ref_cost: float | None) -> Row:
    row: Row = {"scenario": name, "m": problem.m, "planner": planner, "ok": traj is not None, "time_ms": 1e3 * dt}
    if traj is None:
        return {**row, "message": msg}
    cost = snap_cost(traj)
    same_times = np.array_equal(traj.times, problem.times)
    rep = verify(traj, problem) if same_times else None
    row.update(cost=cost, cost_vs_global=cost / ref_cost if ref_cost else float("nan"),
               verified="stretched" if rep is None else rep.ok,
               verify_failures="; ".join(rep.failures()) if rep is not None else "")
    row.update(violations(traj, problem))
    return row


def compare(name: str, problem: Problem) -> list[Row]:
    rows: list[Row] = []
    g = plan_global(problem)
    ref = g.stats["integrated_snap"] if g.ok else None
    it = plan_iterative(problem, IterativeOptions())
    rows.append(_row(name, "ours iterative", it.trajectory, it.stats.get("time_total", 0.0), it.message, problem, ref))
    rows.append(_row(name, "ours global", g.trajectory, g.stats.get("time_total", 0.0), g.message, problem, ref))
    for algorithm, maxiter, label in (("closed-form", None, "closed-form"),
                                      ("constrained", CONSTRAINED_MAXITER, f"constrained it{CONSTRAINED_MAXITER}")):
        traj, dt, msg = minsnap_plan(problem, algorithm, maxiter)
        rows.append(_row(name, f"minsnap {label}", traj, dt, msg, problem, ref))
    return rows


def conversion_error(problem: Problem) -> float:
    """Max |position| difference between minsnap's own evaluation and our Bézier conversion."""
    import minsnap_trajectories as ms

    traj, _, _ = minsnap_plan(problem, "closed-form")
    assert traj is not None
    refs = [ms.Waypoint(time=float(t), position=w, velocity=np.zeros(3), acceleration=np.zeros(3),
                        jerk=np.zeros(3), snap=np.zeros(3)) if i in (0, problem.m - 1)
            else ms.Waypoint(time=float(t), position=w) for i, (t, w) in enumerate(zip(problem.times,
                                                                                      problem.waypoints, strict=True))]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        poly = ms.generate_trajectory(refs, degree=DEGREE, idx_minimized_orders=4, num_continuous_orders=5)
    t = np.linspace(problem.times[0], problem.times[-1], 2000)
    theirs = ms.compute_trajectory_derivatives(poly, t, 5)
    err = max(float(np.max(np.abs(theirs[k] - traj.evaluate(t, k)) / (1.0 + np.abs(theirs[k]).max())))
              for k in range(5))
    return err


def scenario1() -> Problem:
    return load_scenario(json.loads((ROOT / "examples" / "scenario1.json").read_text())).problem


COLS = ["scenario", "m", "planner", "ok", "time_ms", "cost_vs_global", "verified", "v_viol", "a_viol",
        "j_viol", "s_viol", "bound_hull", "v_use", "a_use", "j_use", "s_use", "corridor_viol", "corridor_hull"]


def run(n_random: int = 5, n_fast: int = 2) -> list[Row]:
    rows = compare("scenario1", scenario1())
    for seed in range(n_random):
        sc = random_scenario(seed)
        rows += compare(sc.name, sc.problem)
        if seed < n_fast:
            fast = faster(sc, FAST_FACTOR)
            rows += compare(fast.name, fast.problem)
    return rows


def default_constrained_status() -> str:
    """What the constrained solver says with its default options on scenario 1."""
    traj, dt, msg = minsnap_plan(scenario1(), "constrained")
    return f"{'planned' if traj is not None else 'failed: ' + msg} ({dt:.2f} s)"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--random", type=int, default=5, help="random cluttered scenarios (benchmarks/quality.py)")
    ap.add_argument("--fast", type=int, default=2, help="of those, how many also flown faster")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    try:
        import minsnap_trajectories  # noqa: F401
    except ImportError:
        print(INSTALL_HINT)
        return 0
    print(f"power->Bezier conversion error on scenario 1 (relative, orders 0-4): {conversion_error(scenario1()):.2e}")
    print(f"minsnap constrained with default options (maxiter 100), scenario 1: {default_constrained_status()}")
    rows = run(args.random, args.fast)
    print("violations: > 0 is outside the bound/corridor (m, m/s, ...); *_use: max |x^(k)| / bound on the curve")
    print(table(rows, COLS))
    for r in rows:
        if r.get("verify_failures"):
            print(f"  {r['scenario']} {r['planner']}: {r['verify_failures']}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
