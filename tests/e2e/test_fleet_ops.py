"""A fleet through one router, operator side (issue 24.2 and 24.5), with real processes on loopback:
`python -m companion router`, two `sitl_mock --home` placed 10 m apart, two companions joining
the router as Zenoh clients with a shared `[fleet] origin`; `python -m companion fleet` lists both
(liveliness and status), `send --vehicle alpha,bravo` arms both with one exact put each, each
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
# where each mock stands: alpha at the fleet origin, bravo 10 m north and 4 m east of it
HOMES = {"alpha": FLEET, "bravo": ned_to_lla([10.0, 4.0, 0.0], FLEET)}
GROUND_Z = 1.6  # the PX4 mock's local origin is 1.6 m above the ground


def _config(vehicle: str, router: int, mav_port: int) -> str:
    return f"""
[vehicle]
id = "{vehicle}"

[zenoh]
mode = "client"
connect = ["tcp/127.0.0.1:{router}"]
multicast_scouting = false

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

    def start(self) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(REPO)}

        def spawn(name: str, *cmd: str) -> None:
            self.procs.append(subprocess.Popen([sys.executable, *cmd], cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                                               stderr=open(self.tmp / f"{name}.err", "wb")))  # noqa: SIM115

        spawn("router", "-m", "companion", "router", "--listen", f"tcp/127.0.0.1:{self.router}")
        for vehicle, home in HOMES.items():
            mav = free_port(socket.SOCK_DGRAM)
            spawn(f"{vehicle}-mock", "-m", "sitl_mock", "--endpoint", f"udpin:127.0.0.1:{mav}", "--px4-ready-after",
                  "0", "--response", "ideal", "--home", ",".join(f"{v:.9f}" for v in home))
            cfg = self.tmp / f"{vehicle}.toml"
            cfg.write_text(_config(vehicle, self.router, mav))
            spawn(vehicle, "-m", "companion", "run", "--config", str(cfg))
        zc = zenoh.Config()
        zc.insert_json5("mode", '"client"')
        zc.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{self.router}"]))
        zc.insert_json5("scouting/multicast/enabled", "false")
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
        return subprocess.run([sys.executable, "-m", "companion", *args, "--connect", f"tcp/127.0.0.1:{self.router}"],
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
    want = {"alpha": [0.0, 0.0, -GROUND_Z], "bravo": [10.0, 4.0, -GROUND_Z]}
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
    assert "alpha" in table.stdout and "bravo" in table.stdout


def test_fleet_says_when_nobody_is_present(fleet: Fleet) -> None:
    out = fleet.cli("fleet", "--prefix", "nobody", "--wait", "0.5")
    assert out.returncode == 3 and "no vehicle present" in out.stderr


def test_a_fleet_obstacle_reaches_each_vehicle_in_its_own_frame(fleet: Fleet) -> None:
    post = {"origin": "fleet", "add": [{"id": "post", "vertices": [[5, 2, 0], [6, 2, 0], [5, 3, 0], [5, 2, -3]]}]}
    out = fleet.cli("send", "obstacles", "-", "--vehicle", "alpha,bravo", "--wait", "10", stdin=json.dumps(post))
    assert out.returncode == 0, (out.stdout, out.stderr)
    events = [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
    assert {e["vehicle"] for e in events if e.get("type") == "accepted"} == set(HOMES), events
    fleet.wait(lambda s: all("post" in (s.get(v, {}).get("obstacles") or []) for v in HOMES), 5, "obstacle held")


def test_send_fans_a_command_out_to_each_vehicle(fleet: Fleet) -> None:
    out = fleet.cli("send", "command", "examples/arm.json", "--vehicle", "alpha,bravo", "--wait", "20")
    assert out.returncode == 0, (out.stdout, out.stderr)
    assert "alpha 0, bravo 0" in out.stderr
    fleet.wait(lambda s: all(s.get(v, {}).get("armed") for v in HOMES), 5, "both armed")
    # a vehicle that is not there: its own code, and the others' success does not hide it
    miss = fleet.cli("send", "command", "examples/hold.json", "--vehicle", "nobody,alpha", "--wait", "3")
    assert miss.returncode == 3 and "nobody 3" in miss.stderr, miss.stderr
