"""The other vehicles' trajectories as a companion keeps them (companion.traffic): the message's
fleet part read back into the fleet frame on the system clock, proposals that expire or are
replaced, and a vanished vehicle's reservation widened by its bound speed x the time since."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np

from companion.geodesy import Placement
from companion.traffic import Traffic, from_time, read_claim, to_fleet, to_local
from companion.wire.encode import encode_trajectory
from planner_core import Trajectory, hold

PL = Placement(np.array([10.0, 4.0, -1.6]), np.eye(3))


def _line(a: list[float], b: list[float], t0: float, t1: float) -> Trajectory:
    cp = np.linspace(a, b, 10)[None]
    return Trajectory(np.array([t0, t1]), cp, None, {})


def _message(traj: Trajectory, commit: str, seq: int, time_base: float, **extra: object) -> dict:
    fleet = {"commit": commit, "seq": seq, "priority": 0, "time_base": time_base,
             "offset_ned": PL.offset.tolist(), "rotation": PL.rotation.tolist(), "radius": 0.3, "bound_speed": 2.0,
             **extra}
    return json.loads(encode_trajectory(traj, fleet))


def test_a_message_reads_back_in_the_fleet_frame_on_the_system_clock() -> None:
    local = _line([0, 0, -3], [10, 0, -3], 2.0, 7.0)
    claim = read_claim(_message(local, "committed", 4, 1000.0), "drone2")
    assert claim is not None and claim.committed and claim.seq == 4 and claim.bound_speed == 2.0
    assert np.allclose(claim.trajectory.times, [1002.0, 1007.0])
    assert np.allclose(claim.trajectory.control_points[0, 0], [10, 4, -4.6])
    back = to_local(claim.trajectory, PL, 1000.0)
    assert np.allclose(back.control_points, local.control_points) and np.allclose(back.times, local.times)
    assert np.allclose(to_fleet(local, PL, 1000.0).control_points, claim.trajectory.control_points)
    assert read_claim({"segments": []}, "x") is None  # no fleet part: not a fleet trajectory
    assert read_claim({"fleet": {}, "segments": [{"t0": 0}]}, "x") is None


def test_from_time_cuts_exactly_and_holds_after_the_end() -> None:
    tr = _line([0, 0, 0], [10, 0, 0], 0.0, 10.0)
    cut = from_time(tr, 4.0)
    assert cut.times[0] == 4.0 and np.allclose(cut.evaluate(7.0), tr.evaluate(7.0))
    after = from_time(tr, 12.0)
    assert np.allclose(after.control_points, hold(np.array([10.0, 0, 0]), 12.0).control_points)


def test_proposals_expire_or_are_replaced_by_the_commit() -> None:
    t = Traffic("drone1")
    tr = _line([0, 0, -3], [10, 0, -3], 0.0, 5.0)
    prop = read_claim(_message(tr, "proposed", 2, 100.0, expires=50.0), "drone2")
    assert prop is not None and t.heard(prop)
    assert [c.seq for c in t.live(49.0)] == [2]
    assert t.live(51.0) == []  # expired
    assert t.heard(prop)
    com = read_claim(_message(tr, "committed", 2, 100.0), "drone2")
    assert com is not None and t.heard(com)
    assert [(c.seq, c.committed) for c in t.live(60.0)] == [(2, True)]
    old = read_claim(_message(tr, "committed", 1, 100.0), "drone2")
    assert old is not None and not t.heard(old)  # older than what is held
    assert not t.heard(read_claim(_message(tr, "committed", 9, 100.0), "drone1"))  # our own


def test_a_vanished_vehicle_stays_reserved_and_its_reservation_grows() -> None:
    t = Traffic("drone1")
    c = read_claim(_message(hold(np.array([0.0, 0.0, -3.0]), 0.0), "committed", 3, 100.0), "drone3")
    assert c is not None and t.heard(c)
    t.liveliness("drone3", False, now=200.0)
    assert t.lost() == ["drone3"] and t.widening("drone3", 205.0) == 2.0 * 5.0
    got = t.neighbours(PL, 100.0, 3.0, 0.05, now=205.0)
    assert got is not None
    nb, claims = got
    assert [x.vehicle for x in claims] == ["drone3"]
    n2 = replace(nb, speed=1.0)
    # s' = s + (v + v_k) eps grew by exactly the widening (10 m)
    assert abs(n2.required(0) - (3.0 + (1.0 + 2.0) * 0.05 + 10.0)) < 1e-9
    # a point right next to its hold cannot be certified; one far enough can
    ours_near = hold(np.array([-5.0, -4.0, -1.4]), 100.0)  # fleet (5, 0, -3): 6.6 m from its hold
    checks = t.check(ours_near, PL, 100.0, 3.0, 0.05, 1.0, now=205.0)
    assert checks[0][1] is None
    ours_far = hold(np.array([20.0, -4.0, -1.4]), 100.0)  # fleet (30, 0, -3): 20.7 m
    assert t.check(ours_far, PL, 100.0, 3.0, 0.05, 1.0, now=205.0)[0][1] is not None
    t.liveliness("drone3", True, now=210.0)
    assert t.lost() == [] and t.widening("drone3", 211.0) == 0.0
