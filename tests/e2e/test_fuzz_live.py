"""A bounded live fuzz run (issue 14, item 7): hostile messages against a flying mock.

The vehicle flies a long mission on the PX4 mock while a few hundred hostile messages arrive
on every inbound key (mutated and generated payloads that the decoder must refuse, an
oversized payload, a flood): zero crashes (the companion keeps running and completes the
mission), zero hangs (status keeps coming), every message answered with a `rejected` event
naming a reason, and the largest setpoint gap below 60 ms at 50 Hz (the mock's log).
"""

from __future__ import annotations

import json
import random
import time
import tomllib
from typing import Any

import pytest
import zenoh
from e2e_rig import Rig, arrival_gap, max_gap, setpoints, stream_problem

from companion.config import config_from_dict
from companion.wire.messages import KINDS, MessageError, read

pytestmark = pytest.mark.slow

N_HOSTILE = 400


@pytest.fixture(scope="module")
def rig(rig_factory: Any) -> Rig:
    r: Rig = rig_factory("px4")
    r.ensure_airborne()
    return r


def _base(kind: str, rnd: random.Random) -> dict[str, Any]:
    v = [rnd.uniform(-5, 5), rnd.uniform(-5, 5), -1.0]
    cube = [[x, y, z] for x in (15, 16) for y in (15, 16) for z in (-2, -1)]
    return {
        "mission": {"id": f"h{rnd.randrange(99)}", "waypoints": [v, v], "durations": [1.0, 2.0]},
        "obstacles": {"add": [{"id": "h", "vertices": cube}]},
        "change": {"move_waypoint": {"index": 1, "position": v}},
        "command": {"command": "arm"},
    }[kind]


HOSTILE_VALUES: list[Any] = [-1, 1.5, -1e300, 1e300, "x" * 300, None, True, [], {}, [[1e99, 0, 0]],
                             [[0, 0, 0]] * 40, {"A": -1, "b": -1}, "9" * 50]


def _hostile(kind: str, rnd: random.Random) -> bytes:
    """A payload for `kind` that is wrong in one of many ways."""
    obj = _base(kind, rnd)
    how = rnd.randrange(8)
    if how == 0:  # a field replaced by a hostile value
        key = rnd.choice(sorted(obj))
        obj[key] = rnd.choice(HOSTILE_VALUES)
    elif how == 1:  # a field the message does not take
        obj[rnd.choice(["altitude", "speed", "x" * 200, "A"])] = 3
    elif how == 2:
        return json.dumps(obj).replace("1", "9" * rnd.choice([40, 400, 5000]), 1).encode()
    elif how == 3:
        return b"[" * rnd.choice([20, 1000, 100_000])
    elif how == 4:
        text = json.dumps(obj)
        return text[: rnd.randrange(len(text))].encode()
    elif how == 5:
        return bytes(rnd.randrange(256) for _ in range(rnd.randrange(1, 64)))
    elif how == 6 and kind == "obstacles":
        obj = {"add": [{"id": "flat", "A": [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
                        "b": rnd.choice([[0, 0, 1, 1, 1, 1], [1, 1, 1, 1, 1, -5], [900, 900, 1, 1, 1, 1]])}]}
    elif how == 6:
        obj["frame"] = "ecef"
    else:
        obj = {"command": "takeoff", "altitude": int("9" * 30)} if kind == "command" else [obj]
    return json.dumps(obj).encode()


def answered(rejected: list[dict[str, Any]]) -> int:
    """Messages answered: a rejection each, or one rejection for n messages dropped from a full queue."""
    return sum(int(e.get("dropped", 1)) for e in rejected)


def test_hostile_messages_while_flying(rig: Rig) -> None:
    cfg = config_from_dict(tomllib.loads(rig.config_text()))
    rnd = random.Random(14)
    cases: list[tuple[str, bytes]] = []
    while len(cases) < N_HOSTILE:
        kind = rnd.choice(KINDS)
        payload = _hostile(kind, rnd)
        if isinstance(read(kind, payload, cfg), MessageError):  # only what must be refused
            cases.append((kind, payload))
    cases.append(("mission", b" " * (2 << 20)))  # oversized: refused from its size

    lap = [[3.0, -3.0, -1.0], [3.0, 3.0, -1.2], [-3.0, 3.0, -1.0], [-3.0, -3.0, -1.2]]
    mission = {"id": "fuzz-laps", "frame": "ned", "waypoints": lap * 2 + [[0.0, 0.0, -1.0]]}
    since = rig.mark()
    t0 = rig.mock_time()
    rig.put("mission", mission)
    rig.wait_event(lambda e: e["type"] == "accepted" and e.get("mission") == "fuzz-laps", 10, "mission accepted", since)
    sent_at = time.monotonic()
    for i, (kind, payload) in enumerate(cases):
        # BLOCK: under congestion zenoh drops a put by default; every case must arrive
        rig.session.put(rig.key(kind), payload, congestion_control=zenoh.CongestionControl.BLOCK)
        if i % 20 == 19:
            time.sleep(0.1)  # a few hundred in ~2-4 s; the flood below is faster
    deadline = time.monotonic() + 20
    rejected: list[dict[str, Any]] = []
    while time.monotonic() < deadline:
        rejected = [e for e in rig.events_since(since) if e["type"] == "rejected"]
        if answered(rejected) >= len(cases):
            break
        time.sleep(0.1)
    answered_in = time.monotonic() - sent_at
    events = rig.events_since(since)
    errors = [e for e in events if e["type"] == "error"]
    per_kind = {k: sum(1 for e in rejected if e.get("key") == k) for k in KINDS}
    assert answered(rejected) == len(cases), (answered(rejected), len(cases), per_kind)
    assert all(e.get("reason") and len(e["message"]) <= 700 for e in rejected)
    assert any("max_message_bytes" in e["reason"] for e in rejected)
    assert not [e for e in errors if "internal error" in e["message"]], errors
    # still flying the mission, still answering
    assert rig.state() == "STREAMING"
    rig.wait_event(lambda e: e["type"] == "mission_complete" and e.get("mission") == "fuzz-laps", 60,
                   "mission complete", since)
    t1 = rig.mock_time()
    log = rig.log()
    sps = setpoints(log, t0, t1)
    gap = max_gap(sps)
    by_kind = {k: sum(1 for kk, _ in cases if kk == k) for k in KINDS}
    print(f"\nlive fuzz: {len(cases)} hostile messages {by_kind}, {len(rejected)} rejected with a reason, "
          f"{sum(int(e.get('dropped', 0)) for e in rejected)} dropped from a full queue, 0 crashes, answered within {answered_in:.1f} s; {len(sps)} setpoints, largest gap {gap * 1000:.1f} ms, "
          f"largest arrival gap {arrival_gap(sps) * 1000:.1f} ms")
    assert stream_problem(sps) is None
    assert arrival_gap(sps) <= 0.5
    for proc in rig.procs:
        assert proc.poll() is None
