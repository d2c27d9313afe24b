"""Separation between vehicles through one router (issue 24.3-4), real processes on loopback:
`python -m companion router` (the shipped secured configuration, TLS off), three `sitl_mock --home`
on a circle of 10 m about the fleet origin, three companions as clients with `[fleet] separation`.
One `send --vehicle drone1,drone2,drone3` gives each a crossing mission (to the opposite side,
timed to meet in the middle) at the same instant. Checked: all complete; every committed
trajectory certifies against every other committed at the same time (verify_separation on the
certificate); the flown positions keep separation - tracking allowance; a vehicle that vanishes
stays reserved (its hold cannot be flown into)."""

from __future__ import annotations

import contextlib
import json
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import pytest
import test_fleet_ops as ops

from companion.geodesy import Placement, ned_to_lla
from companion.traffic import Claim, read_claim
from planner_core import Trajectory, hold
from planner_core.separation import certify_separation, verify_separation
from planner_core.trajectory import split_at

R = 10.0
ANGLES = {"drone1": 90.0, "drone2": 210.0, "drone3": 330.0}
UNIT = {v: np.array([np.cos(np.deg2rad(a)), np.sin(np.deg2rad(a)), 0.0]) for v, a in ANGLES.items()}
HOMES = {v: ned_to_lla(R * u, ops.FLEET) for v, u in UNIT.items()}
USERS = {**ops.USERS, "drone3": "d3-secret"}
SEPARATION = 3.0


class Recorder:
    """Trajectory messages (committed, with their fleet part) and telemetry in the fleet frame."""

    def __init__(self, fleet: ops.Fleet) -> None:
        self.fleet = fleet
        self.lock = threading.Lock()
        self.committed: dict[tuple[str, int], tuple[float, Claim]] = {}
        self.proposed = 0
        self.positions: dict[str, list[tuple[float, np.ndarray]]] = {v: [] for v in HOMES}
        fleet.session.declare_subscriber("bezier/*/trajectory", self._trajectory)
        fleet.session.declare_subscriber("bezier/*/telemetry", self._telemetry)

    def _trajectory(self, sample: Any) -> None:
        vehicle = str(sample.key_expr).split("/")[1]
        with contextlib.suppress(ValueError):
            claim = read_claim(json.loads(sample.payload.to_bytes()), vehicle)
            if claim is None:
                return
            with self.lock:
                if not claim.committed:
                    self.proposed += 1
                else:
                    self.committed.setdefault((vehicle, claim.seq), (time.time(), claim))

    def _telemetry(self, sample: Any) -> None:
        vehicle = str(sample.key_expr).split("/")[1]
        with contextlib.suppress(ValueError):
            body = json.loads(sample.payload.to_bytes())
            fl = (self.fleet.statuses.get(vehicle) or {}).get("fleet") or {}
            if body.get("position") is None or not fl.get("placed"):
                return
            pl = Placement(np.asarray(fl["offset_ned"]), np.asarray(fl["rotation"]))
            with self.lock:
                self.positions[vehicle].append((float(body["time"]), pl.to_fleet(body["position"])))


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[ops.Fleet, Recorder]]:
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ops, "HOMES", HOMES)
        mp.setattr(ops, "USERS", USERS)
        f = ops.Fleet(tmp_path_factory.mktemp("fleet-sep"))
        try:
            f.start()
            rec = Recorder(f)
            f.wait(lambda s: all((s.get(v, {}).get("fleet") or {}).get("placed") and s[v].get("link") for v in HOMES),
                   40, "three companions linked and placed")
            yield f, rec
        finally:
            f.stop()


def _from(traj: Trajectory, t: float) -> Trajectory:
    """What is left of a trajectory from t on (exact; a trajectory ended by then holds its end)."""
    if t >= traj.times[-1]:
        return hold(traj.control_points[-1, -1], t)
    cut, k = split_at(traj, t)
    return Trajectory(cut.times[k:], cut.control_points[k:], None, {})


def _send(f: ops.Fleet, kind: str, body: dict[str, Any], vehicles: str, wait: float = 30.0) -> Any:
    return f.cli("send", kind, "-", "--vehicle", vehicles, "--wait", str(wait), stdin=json.dumps(body))


def test_crossing_missions_are_separated(fleet: tuple[ops.Fleet, Recorder]) -> None:
    f, rec = fleet
    out = _send(f, "command", {"command": "arm"}, "drone1,drone2,drone3")
    assert out.returncode == 0, (out.stdout, out.stderr)
    out = _send(f, "command", {"command": "takeoff", "altitude": 3.0}, "drone1,drone2,drone3")
    assert out.returncode == 0, (out.stdout, out.stderr)
    f.wait(lambda s: all(s[v]["state"] == "READY" for v in HOMES), 20, "all airborne")
    z = float(np.mean([p[-1][1][2] for p in rec.positions.values()]))
    # each to the opposite side through the middle, the same timing: they would meet there
    missions = {v: {"id": f"cross-{v}", "origin": "fleet",
                    "waypoints": [(k * R * u + [0, 0, z]).round(3).tolist() for k in (0.5, -0.5, -1.0)],
                    "durations": [5.0, 3.0]} for v, u in UNIT.items()}
    t0 = time.time()
    with ThreadPoolExecutor(3) as pool:  # at the same instant
        outs = list(pool.map(lambda vm: _send(f, "mission", vm[1], vm[0]), missions.items()))
    for o in outs:
        assert o.returncode == 0, (o.stdout, o.stderr)
    f.wait(lambda s: all(s[v]["state"] == "HOLDING" and s[v]["mission"] for v in HOMES), 40, "all crossings complete")
    with f.lock:
        done = {e["vehicle"] for e in f.events if e.get("type") == "mission_complete"}
        accepted = [e for e in f.events if e.get("type") == "accepted" and e.get("key") == "mission"]
    assert done == set(HOMES)
    delays = [e.get("fleet_delay") for e in accepted if e.get("fleet_delay")]
    assert delays, "the crossing needed no deconfliction: the test does not test it"
    # every committed trajectory against every other committed at the same time (from then on)
    with rec.lock:
        committed = sorted(rec.committed.values(), key=lambda x: x[0])
    checked = 0
    for i, (t, c) in enumerate(committed):
        if t < t0:
            continue
        latest: dict[str, Claim] = {}
        for _t2, c2 in committed[: i + 1]:
            latest[c2.vehicle] = c2
        for v, other in latest.items():
            if v == c.vehicle:
                continue
            a, b = _from(c.trajectory, t), _from(other.trajectory, t)
            chk = certify_separation(a, b, SEPARATION)
            assert chk.ok, (c.vehicle, c.seq, v, other.seq, chk.message)
            assert chk.certificate is not None
            assert verify_separation(a, b, chk.certificate).ok
            checked += 1
    assert checked >= 3
    # the flown positions (telemetry at 20 Hz, matched to 50 ms)
    allowance = f.statuses["drone1"]["tracking_allowance"]
    worst = np.inf
    with rec.lock:
        tracks = {v: [(t, p) for t, p in ps if t >= t0] for v, ps in rec.positions.items()}
    names = sorted(tracks)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            tb = np.array([t for t, _ in tracks[b]])
            pb = np.array([p for _, p in tracks[b]])
            for t, p in tracks[a]:
                k = int(np.argmin(np.abs(tb - t)))
                if abs(tb[k] - t) <= 0.05:
                    worst = min(worst, float(np.linalg.norm(p - pb[k])))
    assert worst >= SEPARATION - allowance, worst
    assert rec.proposed >= 3  # every mission went through a proposal
    # each companion checked the certificates the others published against its trajectory
    dec = {v: f.statuses[v]["fleet"]["deconfliction"] for v in HOMES}
    assert all(d["certificates_refused"] == 0 for d in dec.values()), dec
    assert sum(d["certificates_verified"] for d in dec.values()) >= 1, dec


def test_a_vehicle_that_vanishes_stays_reserved(fleet: tuple[ops.Fleet, Recorder]) -> None:
    f, rec = fleet
    f.wait(lambda s: all(s.get(v, {}).get("state") == "HOLDING" for v in HOMES), 40, "holding after the crossing")
    with rec.lock:
        hold3 = rec.positions["drone3"][-1][1]
    f.procs[-1].terminate()  # drone3's companion (spawned last)
    f.procs[-1].wait(15)
    f.wait(lambda s: "drone3" in ((s["drone1"].get("fleet") or {}).get("deconfliction") or {}).get("lost", []), 10,
           "drone1 sees drone3 lost")
    since = len(f.events)
    out = _send(f, "mission", {"id": "into-drone3", "origin": "fleet", "waypoints": [hold3.round(3).tolist()]},
                "drone1", wait=15)
    assert out.returncode != 0, out.stdout
    with f.lock:
        rej = [e for e in f.events[since:] if e["vehicle"] == "drone1" and e.get("type") == "rejected"]
    assert rej and "separation" in rej[-1]["message"] and "drone3" in rej[-1]["message"], rej
