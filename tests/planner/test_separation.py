"""Separation between two vehicles' trajectories (planner_core.separation): certificates that must
hold in continuous time, refusals that must name the right interval, and plans against neighbours."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from planner_core import (
    Bounds,
    MoveWaypoint,
    Neighbours,
    Problem,
    ReplanOptions,
    SeparationCertificate,
    SeparationStatus,
    Trajectory,
    certify_separation,
    common_pieces,
    plan,
    replan,
    separation_rows,
    speed_bound,
    verify_separation,
)
from planner_core.bezier import segments_from_jets
from planner_core.problem import FloatArray
from planner_core.separation import near_pairs, space_time_boxes, with_neighbours

BOUNDS = Bounds.symmetric(5.0, 5.0, 20.0, 100.0)


def line(p0: list[float], p1: list[float], t0: float, t1: float, pieces: int = 3) -> Trajectory:
    """Rest to rest along a straight line, `pieces` segments (C^4, built from jets, no planner)."""
    a, b = np.asarray(p0, float), np.asarray(p1, float)
    times = np.linspace(t0, t1, pieces + 1)
    s = (times - t0) / (t1 - t0)
    # smooth-step position along the line with its time derivatives: s^5-ish polynomial is enough
    # here; we only need a valid C^4 piecewise curve, so take jets of x(t) = a + (b - a) h(s)
    h = [10 * s**3 - 15 * s**4 + 6 * s**5, 30 * s**2 - 60 * s**3 + 30 * s**4, 60 * s - 180 * s**2 + 120 * s**3,
         60 - 360 * s + 360 * s**2, -360 + 720 * s]
    T = t1 - t0
    jets = np.stack([np.outer(h[k] / T**k, b - a) for k in range(5)], axis=1)
    jets[:, 0] += a
    return Trajectory(times, segments_from_jets(jets, np.diff(times)))


def random_trajectory(rng: np.random.Generator, t0: float, n: int = 3) -> Trajectory:
    times = t0 + np.concatenate([[0.0], np.cumsum(rng.uniform(0.5, 2.0, n))])
    jets = rng.normal(size=(n + 1, 5, 3)) * np.array([4.0, 2.0, 2.0, 4.0, 8.0])[None, :, None]
    return Trajectory(times, segments_from_jets(jets, np.diff(times)))


def sampled_min_distance(a: Trajectory, b: Trajectory, n: int = 20001) -> float:
    lo, hi = max(a.t0, b.t0), max(a.t_end, b.t_end) + 1.0
    ts = np.linspace(lo, hi, n)
    return float(np.linalg.norm(a.evaluate(ts) - b.evaluate(ts), axis=1).min())


# --- certificates --------------------------------------------------------------------------------


def test_common_pieces_are_the_same_curves() -> None:
    rng = np.random.default_rng(3)
    a, b = random_trajectory(rng, 0.0, 4), random_trajectory(rng, 0.7, 3)
    knots, pa, pb = common_pieces(a, b)
    assert knots[0] == pytest.approx(0.7) and knots[-1] == pytest.approx(max(a.t_end, b.t_end))
    assert set(np.round(b.times, 9)) <= set(np.round(knots, 9))
    from planner_core.bezier import bernstein_basis

    u = np.linspace(0.0, 1.0, 7)
    for i in range(knots.size - 1):
        ts = knots[i] + u * (knots[i + 1] - knots[i])
        np.testing.assert_allclose(bernstein_basis(9, u) @ pa[i], a.evaluate(ts), atol=1e-9)
        np.testing.assert_allclose(bernstein_basis(9, u) @ pb[i], b.evaluate(ts), atol=1e-9)


def test_offset_crossing_is_certified_and_distance_holds_densely() -> None:
    a = line([-10, 0, 0], [10, 0, 0], 0.0, 6.0)
    b = line([0, -10, 0], [0, 10, 0], 2.5, 8.5)  # crosses the same point 2.5 s later
    chk = certify_separation(a, b, 2.0)
    assert chk.ok and chk.certificate is not None, chk.message
    assert sampled_min_distance(a, b) >= 2.0
    assert chk.min_gap >= 2.0 and chk.min_gap <= sampled_min_distance(a, b) + 1e-9
    assert verify_separation(a, b, chk.certificate).ok
    # the certificate survives its wire form
    again = SeparationCertificate.from_dict(chk.certificate.to_dict())
    assert verify_separation(a, b, again).ok


def test_crossing_that_meets_is_refused_with_the_right_interval() -> None:
    a = line([-10, 0, 0], [10, 0, 0], 0.0, 6.0)
    b = line([0, -10, 0], [0, 10, 0], 0.0, 6.0)  # both at the origin at t = 3
    chk = certify_separation(a, b, 1.0)
    assert chk.status is SeparationStatus.TOO_CLOSE and chk.certificate is None
    assert chk.span is not None and chk.span[0] <= 3.0 <= chk.span[1]
    knots, _, _ = common_pieces(a, b)
    assert chk.interval == int(np.searchsorted(knots, 3.0, side="right") - 1) or knots[chk.interval + 1] == 3.0
    assert chk.shortfall > 0.0
    # a forged certificate (the planes of a safe pair over the same span) is refused
    safe = certify_separation(a, line([0, -10, 4], [0, 10, 4], 0.0, 6.0), 1.0).certificate
    assert safe is not None
    bad = verify_separation(a, b, safe)
    assert bad.status is SeparationStatus.TOO_CLOSE and bad.span is not None and bad.interval is not None
    assert bad.shortfall > 0.0 and "interval" in bad.message


def test_an_ended_trajectory_holds_its_last_point() -> None:
    a = line([-10, 0, 0], [0, 0, 0], 0.0, 2.0)  # ends at the origin at t = 2, stays there
    b = line([0, -10, 0.5], [0, 10, 0.5], 2.0, 8.0)  # passes 0.5 m above the origin at t = 5
    chk = certify_separation(a, b, 1.0)
    assert chk.status is SeparationStatus.TOO_CLOSE
    assert chk.span is not None and chk.span[0] >= a.t_end - 1e-9 and chk.span[0] <= 5.0 <= chk.span[1]
    # the other way round (B is the one that has ended) and a pass 3 m away: certified, hold included
    far = line([0, -10, 3.0], [0, 10, 3.0], 2.0, 8.0)
    ok = certify_separation(far, a, 1.0)
    assert ok.ok and ok.certificate is not None
    assert ok.certificate.times[-1] == pytest.approx(8.0)
    assert verify_separation(far, a, ok.certificate).ok
    # a certificate that stops before the overlap's end does not cover the hold
    cut = replace(ok.certificate, times=ok.certificate.times[:-1], normals=ok.certificate.normals[:-1],
                  offsets=ok.certificate.offsets[:-1])
    assert verify_separation(far, a, cut).status is SeparationStatus.NOT_COVERED


def test_clock_tolerance_widens_the_margin() -> None:
    a = line([-10, 0, 0], [10, 0, 0], 0.0, 6.0)
    b = line([-10, 3, 0], [10, 3, 0], 0.0, 6.0)  # parallel, 3 m apart
    plain = certify_separation(a, b, 2.5)
    assert plain.ok
    va, vb = speed_bound(a), speed_bound(b)
    assert va >= 20.0 / 6.0 * 1.875 - 1e-9  # the smooth step's peak speed, bounded from above
    eps = 0.1
    slow = certify_separation(a, b, 2.5, clock_tolerance=eps)
    assert slow.status is SeparationStatus.TOO_CLOSE  # 2.5 + (va + vb) 0.1 > 3
    wide = certify_separation(a, b, 1.5, clock_tolerance=eps)
    assert wide.ok and wide.certificate is not None
    assert wide.certificate.required == pytest.approx(1.5 + (va + vb) * eps)
    assert wide.min_gap >= wide.certificate.required
    # claiming a clock tolerance the planes do not pay for is refused
    claimed = replace(plain.certificate, clock_tolerance=eps, speed_a=va, speed_b=vb)
    assert verify_separation(a, b, claimed).status is SeparationStatus.TOO_CLOSE
    # stating a bound speed below the trajectory's own speed is refused
    low = replace(wide.certificate, speed_a=0.1)
    assert verify_separation(a, b, low).status is SeparationStatus.SPEED


def test_malformed_certificates_are_a_status() -> None:
    a = line([-10, 0, 0], [10, 0, 0], 0.0, 6.0)
    b = line([-10, 5, 0], [10, 5, 0], 0.0, 6.0)
    cert = certify_separation(a, b, 1.0).certificate
    assert cert is not None
    for broken in (replace(cert, normals=np.zeros_like(cert.normals)),
                   replace(cert, times=cert.times[::-1].copy()),
                   replace(cert, offsets=np.append(cert.offsets, 0.0)),
                   replace(cert, offsets=np.full_like(cert.offsets, np.nan))):
        assert verify_separation(a, b, broken).status is SeparationStatus.MALFORMED


def test_fuzz_random_pairs() -> None:
    rng = np.random.default_rng(20261202)
    certified = refused = 0
    for _ in range(40):
        a = random_trajectory(rng, 0.0, int(rng.integers(1, 4)))
        b = random_trajectory(rng, float(rng.uniform(0.0, 2.0)), int(rng.integers(1, 4)))
        b = Trajectory(b.times, b.control_points + rng.uniform(-3.0, 3.0, 3))
        s = float(rng.uniform(0.5, 4.0))
        chk = certify_separation(a, b, s)
        if chk.ok:
            certified += 1
            assert chk.certificate is not None
            assert sampled_min_distance(a, b, 4001) >= s - 1e-9
            assert verify_separation(a, b, chk.certificate).ok
            # moving B onto A's side of the first plane must be caught
            n = chk.certificate.normals[0]
            moved = Trajectory(b.times, b.control_points - 100.0 * n)
            assert not verify_separation(a, moved, chk.certificate).ok
        else:
            refused += 1
            assert chk.span is not None and chk.shortfall > 0.0
    assert certified >= 5 and refused >= 5


def test_rows_on_our_control_points_hold_exactly_where_the_certificate_does() -> None:
    a = line([-10, 0, 0], [10, 0, 0], 0.0, 6.0, pieces=4)
    b = line([0, -10, 0], [0, 10, 0], 2.5, 8.5, pieces=3)
    cert = certify_separation(a, b, 2.0).certificate
    assert cert is not None
    rows = separation_rows(a.times, cert)
    assert rows.violation(a.control_points) <= 1e-9
    # pushing the segment of the tightest row towards B by its slack + 0.5 m breaks that row by 0.5 m
    # (a piece's control points are convex combinations of its segment's: the weights sum to 1)
    np.testing.assert_allclose(rows.weights.sum(axis=1), 1.0, atol=1e-12)
    tight = int(np.argmax(rows.values(a.control_points) - rows.rhs))
    pushed = a.control_points.copy()
    pushed[rows.segment[tight]] += (0.5 - rows.violation(a.control_points)) * rows.normal[tight]
    assert rows.violation(pushed) == pytest.approx(0.5)


# --- broad phase and planning against neighbours ------------------------------------------------


def test_far_neighbours_cost_nothing() -> None:
    ours = line([-10, 0, 0], [10, 0, 0], 0.0, 6.0)
    far = [line([100 + 3 * k, -5, 0], [100 + 3 * k, 5, 0], 0.0, 6.0) for k in range(50)]
    qlo, qhi = space_time_boxes(ours)
    olo = np.concatenate([space_time_boxes(t)[0] for t in far])
    ohi = np.concatenate([space_time_boxes(t)[1] for t in far])
    qi, _ = near_pairs(qlo, qhi, olo, ohi, 2.0)
    assert qi.size == 0
    problem = Problem.from_waypoints([[-10, 0, 0], [0, 0, 0], [10, 0, 0]], [3.0, 3.0], BOUNDS)
    cut, why = with_neighbours(problem, Neighbours(tuple(far), 2.0))
    assert why is None and cut is problem


def _scene() -> tuple[Problem, Trajectory]:
    b = BOUNDS
    neighbour = plan(Problem.from_waypoints([[0, 6, 0], [0, 3, 0]], [2.0], b)).trajectory  # then holds at (0, 3, 0)
    assert neighbour is not None
    ours = Problem.from_waypoints([[-6, 0, 0], [-3, 1.5, 0], [0, 1.6, 0], [3, 1.5, 0], [6, 0, 0]], [1.5] * 4, b)
    return ours, neighbour


def test_plan_with_neighbours_keeps_separation_at_all_sampled_times() -> None:
    ours, neighbour = _scene()
    s = 1.3
    free = plan(ours)
    assert free.ok and free.trajectory is not None
    assert sampled_min_distance(free.trajectory, neighbour) < s  # without the neighbour it comes too close
    res = plan(ours, neighbours=Neighbours((neighbour,), s))
    assert res.ok and res.trajectory is not None, res.message
    assert res.stats["separation"]["ok"]
    assert sampled_min_distance(res.trajectory, neighbour) >= s
    chk = certify_separation(res.trajectory, neighbour, s)
    assert chk.ok and chk.certificate is not None and verify_separation(res.trajectory, neighbour, chk.certificate).ok
    assert res.trajectory.corridors == ours.corridors  # the faces are not left in the plan


def test_plan_refuses_a_waypoint_inside_a_neighbours_reach() -> None:
    ours, neighbour = _scene()
    res = plan(ours, neighbours=Neighbours((neighbour,), 2.0))  # waypoint (0, 1.6) is 1.4 m from the hold
    assert not res.ok and "separation" in res.message


def test_local_replan_with_neighbours_keeps_separation() -> None:
    ours, neighbour = _scene()
    nb = Neighbours((neighbour,), 1.3)
    first = plan(ours, neighbours=nb)
    assert first.ok and first.trajectory is not None
    res = replan(ours, first.trajectory, MoveWaypoint(2, np.array([0.3, 1.5, 0.0])),
                 options=ReplanOptions(neighbours=replace(nb, reference=first.trajectory)))
    assert res.ok and res.trajectory is not None, res.message
    assert res.trajectory.stats["separation"]["ok"]
    assert sampled_min_distance(res.trajectory, neighbour) >= 1.3
    # without the neighbour the same move comes closer than 1.3 m
    bare = replan(ours, first.trajectory, MoveWaypoint(2, np.array([0.3, 1.5, 0.0])))
    assert bare.ok and bare.trajectory is not None
    assert sampled_min_distance(bare.trajectory, neighbour) < 1.3


def test_a_neighbour_crossing_within_one_segment_is_planned_around_with_time_resolved_rows() -> None:
    # one face per segment cannot work here: the neighbour sweeps across our whole first segment's
    # path during its span (crossing x = -5 at t = 5, when we are ~3.5 m past); planes per piece can
    ours = Problem.from_waypoints([[-10, 0, 0], [0, 0, 0], [10, 0, 0]], [6.0, 6.0], BOUNDS)
    neighbour = line([-5, -10, 0], [-5, 10, 0], 2.5, 7.5)
    alone = plan(ours)
    assert alone.ok and alone.trajectory is not None
    assert sampled_min_distance(alone.trajectory, neighbour) < 4.0
    res = plan(ours, neighbours=Neighbours((neighbour,), 4.0))
    assert res.ok and res.trajectory is not None, res.message
    assert "time-resolved" in res.message and res.stats["separation"]["ok"]
    assert sampled_min_distance(res.trajectory, neighbour) >= 4.0
    np.testing.assert_allclose(res.trajectory.waypoints, ours.waypoints)
    (k, cert), = res.stats["separation"]["certificates"]
    assert k == 0 and verify_separation(res.trajectory, neighbour, cert).ok


def test_local_replan_falls_back_to_time_resolved_rows() -> None:
    # our plan was committed before the neighbour: it crosses our segment 1's path within its span
    ours = Problem.from_waypoints([[-15, 0, 0], [-10, 0, 0], [0, 0, 0], [10, 0, 0]], [4.0, 6.0, 6.0], BOUNDS)
    first = plan(ours)
    assert first.ok and first.trajectory is not None
    neighbour = line([-5, -10, 0], [-5, 10, 0], 6.5, 11.5)
    assert sampled_min_distance(first.trajectory, neighbour) < 4.0
    change = MoveWaypoint(2, np.array([0.0, 0.3, 0.0]))
    res = replan(ours, first.trajectory, change, options=ReplanOptions(neighbours=Neighbours((neighbour,), 4.0)))
    assert res.ok and res.trajectory is not None, res.message
    assert res.stats.get("separation_rows") and res.stats["separation"]["ok"]
    assert sampled_min_distance(res.trajectory, neighbour) >= 4.0
    bare = replan(ours, first.trajectory, change)
    assert bare.ok and bare.trajectory is not None
    assert sampled_min_distance(bare.trajectory, neighbour) < 4.0


def test_exact_planes_and_a_clock_tolerance_in_planning() -> None:
    a = line([-10, 0, 0], [10, 0, 0], 0.0, 6.0)
    b = line([0, -10, 0], [0, 10, 0], 2.5, 8.5)
    exact = certify_separation(a, b, 2.0, exact=True)
    assert exact.ok and exact.certificate is not None and verify_separation(a, b, exact.certificate).ok
    ours, neighbour = _scene()
    nb = Neighbours((neighbour,), 1.0, clock_tolerance=0.02)
    res = plan(ours, neighbours=nb)
    assert res.ok and res.trajectory is not None, res.message
    from planner_core.separation import bound_speed

    v_ours = bound_speed(ours.bounds)  # our bound speed from the problem's bounds
    assert nb.for_bounds(ours.bounds).required(0) == pytest.approx(1.0 + (v_ours + speed_bound(neighbour)) * 0.02)
    for _, c in res.stats["separation"]["certificates"]:  # those the broad phase did not settle
        assert c.speed_a == pytest.approx(v_ours) and verify_separation(res.trajectory, neighbour, c).ok
    chk = certify_separation(res.trajectory, neighbour, 1.0, clock_tolerance=0.02,
                             speeds=(v_ours, speed_bound(neighbour)))
    assert chk.ok and chk.certificate is not None
    cert = chk.certificate
    assert cert.required == pytest.approx(1.0 + (v_ours + speed_bound(neighbour)) * 0.02)
    assert verify_separation(res.trajectory, neighbour, cert).ok
    assert sampled_min_distance(res.trajectory, neighbour) >= cert.required


def _cruise(p0: FloatArray, p1: FloatArray, t0: float, t1: float) -> Trajectory:
    times = np.linspace(t0, t1, 3)
    v = (p1 - p0) / (t1 - t0)
    jets = np.zeros((3, 5, 3))
    jets[:, 0] = p0 + (times - t0)[:, None] * v
    jets[:, 1] = v
    return Trajectory(times, segments_from_jets(jets, np.diff(times)))


def test_fuzz_plans_against_random_neighbours_keep_separation_when_accepted() -> None:
    rng = np.random.default_rng(24)
    accepted = 0
    for _ in range(8):
        m = int(rng.integers(3, 6))
        wps = np.cumsum(rng.uniform([3.0, -2.0, -0.5], [6.0, 2.0, 0.5], (m, 3)), axis=0)
        ours = Problem.from_waypoints(wps, np.full(m - 1, 3.0), BOUNDS)
        alone = plan(ours)
        assert alone.ok and alone.trajectory is not None
        others = []
        for _ in range(int(rng.integers(1, 5))):
            mid = alone.trajectory.evaluate(float(rng.uniform(0.0, alone.trajectory.t_end)))
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            tc = float(rng.uniform(-3.0, alone.trajectory.t_end + 3.0))
            others.append(_cruise(mid - 8.0 * d + rng.normal(size=3), mid + 8.0 * d, tc - 2.0, tc + 2.0))
        s = float(rng.uniform(1.0, 2.5))
        res = plan(ours, neighbours=Neighbours(tuple(others), s))
        if not res.ok:
            continue
        accepted += 1
        assert res.trajectory is not None
        for other in others:
            assert sampled_min_distance(res.trajectory, other, 6001) >= s - 1e-9
    assert accepted >= 3


def test_a_plans_certificates_survive_its_json_form() -> None:
    import json

    from planner_core import trajectory_from_dict, trajectory_to_dict

    ours = Problem.from_waypoints([[-10, 0, 0], [0, 0, 0], [10, 0, 0]], [6.0, 6.0], BOUNDS)
    neighbour = line([-5, -10, 0], [-5, 10, 0], 2.5, 7.5)
    res = plan(ours, neighbours=Neighbours((neighbour,), 4.0))
    assert res.ok and res.trajectory is not None
    text = json.dumps(trajectory_to_dict(res.trajectory))
    back = trajectory_from_dict(json.loads(text))
    (k, d), = back.stats["separation"]["certificates"]
    assert k == 0 and verify_separation(back, neighbour, SeparationCertificate.from_dict(d)).ok
