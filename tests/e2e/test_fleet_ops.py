"""A fleet through one router, operator side (issue 24.2 and 24.5), with real processes on loopback:
`python -m companion router` with the shipped secured configuration (user/password and access
control per vehicle; TLS off on loopback), two `sitl_mock --home` placed 10 m apart, two
companions joining the router as Zenoh clients with their own credentials and a shared
`[fleet] origin`; with an operator's credentials, `python -m companion fleet` lists both
(liveliness and status), `send --vehicle drone1,drone2` arms both with one exact put each, each
companion says where its local frame sits in the fleet frame, and a fleet-frame obstacle is taken.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from e2e_rig import REPO, free_port

from companion.geodesy import ned_to_lla

FLEET = (47.397742, 8.545594, 488.0)
# where each mock stands: drone1 at the fleet origin, drone2 10 m north and 4 m east of it
HOMES = {"drone1": FLEET, "drone2": ned_to_lla([10.0, 4.0, 0.0], FLEET)}
USERS = {"drone1": "d1-secret", "drone2": "d2-secret", "operator": "op-secret"}
SHIPPED = REPO / "config" / "zenoh-router-fleet.json5"
GROUND_Z = 1.6  # the PX4 mock's local origin is 1.6 m above the ground


def _client_file(path: Path, user: str, router: int) -> Path:
    """A client's Zenoh configuration (as config/zenoh-vehicle-fleet.json5, without TLS)."""
    path.write_text(json.dumps({
        "mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{router}"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": user, "password": USERS[user]}}}}))
    return path


def _config(vehicle: str, zenoh_file: Path, mav_port: int) -> str:
    return f"""
[vehicle]
id = "{vehicle}"

[zenoh]
config_file = "{zenoh_file}"

[mavlink]
url = "udpout:127.0.0.1:{mav_port}"

[planner]
executor = "thread"

[safety]
# the tests end with both vehicles armed on the ground: a short hand-over check on exit
hold_confirm = 0.5
exit_timeout = 4.0

[fleet]
origin = [{FLEET[0]}, {FLEET[1]}, {FLEET[2]}]
clock_tolerance = 0.05
"""


class Fleet:
    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.router = free_port()
        self.procs: list[subprocess.Popen[bytes]] = []
        self.statuses: dict[str, dict[str, Any]] = {}
        self.events: list[dict[str, Any]] = []
        self.lock = threading.Lock()
        self.session: Any = None
        self.operator = Path()

    def start(self) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(REPO)}

        def spawn(name: str, *cmd: str) -> None:
            self.procs.append(subprocess.Popen([sys.executable, *cmd], cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                                               stderr=open(self.tmp / f"{name}.err", "wb")))  # noqa: SIM115

        # the shipped secured router configuration, with the test's dictionary and no TLS on loopback
        users = self.tmp / "users.txt"
        users.write_text("".join(f"{u}:{p}\n" for u, p in USERS.items()))
        users.chmod(0o600)
        rcfg = zenoh.Config.from_file(str(SHIPPED))
        rcfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users)))
        rcfg.insert_json5("transport/link/tls", json.dumps({}))
        (self.tmp / "router.json").write_text(str(rcfg))
        spawn("router", "-m", "companion", "router", "--config", str(self.tmp / "router.json"),
              "--listen", f"tcp/127.0.0.1:{self.router}")
        self.operator = _client_file(self.tmp / "operator.json", "operator", self.router)
        for vehicle, home in HOMES.items():
            mav = free_port(socket.SOCK_DGRAM)
            spawn(f"{vehicle}-mock", "-m", "sitl_mock", "--endpoint", f"udpin:127.0.0.1:{mav}", "--px4-ready-after",
                  "0", "--response", "ideal", "--home", ",".join(f"{v:.9f}" for v in home))
            cfg = self.tmp / f"{vehicle}.toml"
            cfg.write_text(_config(vehicle, _client_file(self.tmp / f"{vehicle}.json", vehicle, self.router), mav))
            spawn(vehicle, "-m", "companion", "run", "--config", str(cfg))
        zc = zenoh.Config.from_file(str(self.operator))
        deadline = time.monotonic() + 20
        while self.session is None:
            try:
                self.session = zenoh.open(zc)
            except zenoh.ZError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        self.session.declare_subscriber("bezier/*/status", self._status)
        self.session.declare_subscriber("bezier/*/events", self._event)

    def _status(self, sample: Any) -> None:
        with contextlib.suppress(ValueError):
            body = json.loads(sample.payload.to_bytes())
            with self.lock:
                self.statuses[str(sample.key_expr).split("/")[1]] = body

    def _event(self, sample: Any) -> None:
        with contextlib.suppress(ValueError):
            body = json.loads(sample.payload.to_bytes())
            with self.lock:
                self.events.append({"vehicle": str(sample.key_expr).split("/")[1], **body})

    def wait(self, pred: Callable[[dict[str, dict[str, Any]]], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                if pred(dict(self.statuses)):
                    return
            time.sleep(0.1)
        with self.lock:
            raise AssertionError(f"{what}: not within {timeout} s; statuses {self.statuses}; see {self.tmp}")

    def cli(self, *args: str, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "companion", *args, "--zenoh-config", str(self.operator)],
                              capture_output=True, text=True, timeout=60, cwd=REPO, input=stdin,
                              env={**os.environ, "PYTHONPATH": str(REPO)})

    def stop(self) -> None:
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
        for p in reversed(self.procs):
            p.terminate()
        for p in self.procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(5)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    f = Fleet(tmp_path_factory.mktemp("fleet"))
    try:
        f.start()
        f.wait(lambda s: all(s.get(v, {}).get("link") for v in HOMES), 40, "both companions linked")
        yield f
    finally:
        f.stop()


def test_each_companion_places_its_frame_in_the_fleet_frame(fleet: Fleet) -> None:
    fleet.wait(lambda s: all((s.get(v, {}).get("fleet") or {}).get("placed") for v in HOMES), 15, "fleet frame placed")
    want = {"drone1": [0.0, 0.0, -GROUND_Z], "drone2": [10.0, 4.0, -GROUND_Z]}
    for vehicle, offset in want.items():
        st = fleet.statuses[vehicle]["fleet"]
        assert st["source"] in ("gps_global_origin", "home_position"), st
        # the mock's flat earth against WGS-84: ~0.3 % of the distance
        assert all(abs(a - b) < 0.05 for a, b in zip(st["offset_ned"], offset, strict=True)), (vehicle, st)
        assert st["clock_tolerance"] == 0.05
    placed = [e for e in fleet.events if e.get("type") == "fleet_frame"]
    assert {e["vehicle"] for e in placed} >= set(HOMES) or not placed  # said, when heard after we subscribed


def test_fleet_lists_the_vehicles_present(fleet: Fleet) -> None:
    out = fleet.cli("fleet", "--json")
    assert out.returncode == 0, out.stderr
    rows = {r["vehicle"]: r for r in map(json.loads, out.stdout.splitlines())}
    assert set(rows) == set(HOMES), out.stdout
    for r in rows.values():
        assert r["state"] == "IDLE" and r["frame"] == "placed" and r["status"]["session"]
        # the same computer's clock: off by the rounding of status `time` and the round trip only
        assert abs(r["clock_ms"]) <= r["clock_uncertainty_ms"] + 2.0, r
    table = fleet.cli("fleet")
    assert table.returncode == 0 and table.stdout.splitlines()[0].split()[:4] == ["vehicle", "state", "mission",
                                                                                   "progress"]
    assert "drone1" in table.stdout and "drone2" in table.stdout


def test_fleet_says_when_nobody_is_present(fleet: Fleet) -> None:
    out = fleet.cli("fleet", "--prefix", "nobody", "--wait", "0.5")
    assert out.returncode == 3 and "no vehicle present" in out.stderr


def test_a_fleet_obstacle_reaches_each_vehicle_in_its_own_frame(fleet: Fleet) -> None:
    post = {"origin": "fleet", "add": [{"id": "post", "vertices": [[5, 2, 0], [6, 2, 0], [5, 3, 0], [5, 2, -3]]}]}
    out = fleet.cli("send", "obstacles", "-", "--vehicle", "drone1,drone2", "--wait", "10", stdin=json.dumps(post))
    assert out.returncode == 0, (out.stdout, out.stderr)
    events = [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
    assert {e["vehicle"] for e in events if e.get("type") == "accepted"} == set(HOMES), events
    fleet.wait(lambda s: all("post" in (s.get(v, {}).get("obstacles") or []) for v in HOMES), 5, "obstacle held")


def test_send_fans_a_command_out_to_each_vehicle(fleet: Fleet) -> None:
    out = fleet.cli("send", "command", "examples/arm.json", "--vehicle", "drone1,drone2", "--wait", "20")
    assert out.returncode == 0, (out.stdout, out.stderr)
    assert "drone1 0, drone2 0" in out.stderr
    fleet.wait(lambda s: all(s.get(v, {}).get("armed") for v in HOMES), 5, "both armed")
    # a vehicle that is not there: its own code, and the others' success does not hide it
    miss = fleet.cli("send", "command", "examples/hold.json", "--vehicle", "nobody,drone1", "--wait", "3")
    assert miss.returncode == 3 and "nobody 3" in miss.stderr, miss.stderr


def test_the_router_is_the_secured_one(fleet: Fleet) -> None:
    """The fleet above ran through the shipped access control: a session without credentials is
    refused, and drone1's credentials cannot command drone2."""
    zc = zenoh.Config()
    zc.insert_json5("mode", '"client"')
    zc.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{fleet.router}"]))
    zc.insert_json5("scouting/multicast/enabled", "false")
    zc.insert_json5("connect/timeout_ms", "500")
    zc.insert_json5("connect/exit_on_failure", "true")
    with pytest.raises(zenoh.ZError):
        zenoh.open(zc).close()
    d1 = zenoh.open(zenoh.Config.from_file(str(_client_file(fleet.tmp / "d1-tool.json", "drone1", fleet.router))))
    try:
        since = len(fleet.events)
        for _ in range(5):
            d1.put("bezier/drone2/command", b'{"command": "disarm"}')
            time.sleep(0.1)
        time.sleep(0.5)
        with fleet.lock:
            assert not [e for e in fleet.events[since:] if e["vehicle"] == "drone2" and e.get("key") == "command"]
            assert fleet.statuses["drone2"]["armed"]
    finally:
        d1.close()
