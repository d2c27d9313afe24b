"""A fleet's Zenoh router (issue 24.1), with real Zenoh sessions on loopback.

`python -m companion router` as a process: two client sessions exchange puts through it.
The shipped secured router configuration (config/zenoh-router-fleet.json5), opened as the
router opens it, with only the endpoint (an explicit tcp/127.0.0.1 port instead of TLS) and
the dictionary path swapped for the test: vehicle drone1's credentials cannot put under
drone2's keys, drone2 reads drone1's trajectory and liveliness, an operator commands both.
"""

from __future__ import annotations

import json
import os
import signal
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

from companion.config import ZenohConfig
from companion.router import router_config
from companion.wire.zenoh import exposure, zenoh_config

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "config" / "zenoh-router-fleet.json5"
VEHICLE_SHIPPED = REPO / "config" / "zenoh-vehicle-fleet.json5"


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _client(port: int, user: str | None = None, password: str | None = None, timeout_ms: int = 2000) -> Any:
    zc = zenoh.Config()
    zc.insert_json5("mode", '"client"')
    zc.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    zc.insert_json5("scouting/multicast/enabled", "false")
    zc.insert_json5("connect/timeout_ms", str(timeout_ms))
    zc.insert_json5("connect/exit_on_failure", "true")
    if user is not None:
        zc.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
    try:
        return zenoh.open(zc)
    except zenoh.ZError:
        return None


def _wait_until(cond: Callable[[], bool], timeout: float = 3.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.05)
    return cond()


def _wait_port(port: int, proc: subprocess.Popen[str], timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()[1]
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise AssertionError(f"router not listening on {port}")


def test_router_process_relays_puts_between_two_clients() -> None:
    port = _port()
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "companion", "router", "--listen", f"tcp/127.0.0.1:{port}"],
                            cwd=REPO, env=env, stderr=subprocess.PIPE, text=True)
    a = b = None
    try:
        _wait_port(port, proc)
        a, b = _client(port), _client(port)
        assert a is not None and b is not None
        got_a: list[bytes] = []
        got_b: list[bytes] = []
        sa = a.declare_subscriber("bezier/drone1/command", lambda s: got_a.append(s.payload.to_bytes()))
        sb = b.declare_subscriber("bezier/drone2/status", lambda s: got_b.append(s.payload.to_bytes()))
        assert _wait_until(lambda: (b.put("bezier/drone1/command", b"from-b"), bool(got_a))[1])
        assert _wait_until(lambda: (a.put("bezier/drone2/status", b"from-a"), bool(got_b))[1])
        assert got_a[0] == b"from-b" and got_b[0] == b"from-a"
        sa.undeclare()
        sb.undeclare()
    finally:
        for s in (a, b):
            if s is not None:
                s.close()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert f"listening on tcp/127.0.0.1:{port}" in err


def test_router_needs_an_endpoint() -> None:
    r = subprocess.run([sys.executable, "-m", "companion", "router"], cwd=REPO, capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=30)
    assert r.returncode == 2 and "--listen" in r.stderr


# -- the secured fleet configuration: access control per vehicle --------------------------------


USERS = {"drone1": "d1-secret", "drone2": "d2-secret", "operator": "op-secret", "observer": "obs-secret"}


@pytest.fixture(scope="module")
def router(tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    tmp = tmp_path_factory.mktemp("fleet-router")
    users = tmp / "users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in USERS.items()))
    users.chmod(0o600)
    port = _port()
    cfg = router_config([f"tcp/127.0.0.1:{port}"], str(SHIPPED))  # as `router --config` opens it
    cfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users)))
    cfg.insert_json5("transport/link/tls", json.dumps({}))  # TLS is documented, not on loopback
    session = zenoh.open(cfg)
    yield port
    session.close()


class Listener:
    """A client session that records what it receives on some key expressions."""

    def __init__(self, session: Any, *keys: str) -> None:
        self.got: list[tuple[str, bytes]] = []
        self.lock = threading.Lock()
        self.subs = [session.declare_subscriber(k, self._take) for k in keys]

    def _take(self, sample: Any) -> None:
        with self.lock:
            self.got.append((str(sample.key_expr), sample.payload.to_bytes()))

    def has(self, key: str, tag: bytes) -> bool:
        with self.lock:
            return (key, tag) in self.got


def _put_until(session: Any, key: str, tag: bytes, heard: Callable[[], bool], timeout: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        session.put(key, tag)
        time.sleep(0.1)
        if heard():
            return True
    return False


def test_a_vehicle_puts_under_its_own_keys_only(router: int) -> None:
    d1 = _client(router, "drone1", USERS["drone1"])
    d2 = _client(router, "drone2", USERS["drone2"])
    op = _client(router, "operator", USERS["operator"])
    assert d1 is not None and d2 is not None and op is not None
    try:
        # drone2 as its companion subscribes: its inbound keys and the fleet's trajectories;
        # the operator watches everything.
        inbound = Listener(d2, *(f"bezier/drone2/{k}" for k in ("command", "mission", "obstacles", "change")),
                           "bezier/*/trajectory")
        watch = Listener(op, "bezier/**")
        time.sleep(0.3)
        # drone1 publishes its own trajectory and status: drone2 and the operator get them
        assert _put_until(d1, "bezier/drone1/trajectory", b"d1-traj", lambda: inbound.has("bezier/drone1/trajectory",
                                                                                          b"d1-traj"))
        assert _put_until(d1, "bezier/drone1/status", b"d1-status", lambda: watch.has("bezier/drone1/status",
                                                                                      b"d1-status"))
        # drone1's credentials cannot put under drone2's keys: not a command, not a fake trajectory
        for key in ("bezier/drone2/command", "bezier/drone2/mission", "bezier/drone2/trajectory",
                    "bezier/drone2/status"):
            assert not _put_until(d1, key, b"d1-forged", lambda k=key: watch.has(k, b"d1-forged") or  # type: ignore[misc]
                                  inbound.has(k, b"d1-forged"), timeout=0.6), key
        # nor on a wildcard that reaches drone2
        assert not _put_until(d1, "bezier/*/command", b"d1-wild", lambda: inbound.has("bezier/*/command", b"d1-wild"),
                              timeout=0.6)
        # the operator commands drone2 (and the put arrives on its exact key)
        assert _put_until(op, "bezier/drone2/command", b"op-cmd", lambda: inbound.has("bezier/drone2/command",
                                                                                      b"op-cmd"))
    finally:
        for s in (d1, d2, op):
            s.close()


def test_vehicles_see_each_others_liveliness(router: int) -> None:
    d1 = _client(router, "drone1", USERS["drone1"])
    d2 = _client(router, "drone2", USERS["drone2"])
    assert d1 is not None and d2 is not None
    try:
        token = d1.liveliness().declare_token("bezier/drone1/alive")
        # drone1 cannot claim to be drone2 in liveliness either
        fake = d1.liveliness().declare_token("bezier/drone2/alive")

        def alive() -> set[str]:
            return {str(r.ok.key_expr) for r in d2.liveliness().get("bezier/*/alive", timeout=1.0) if r.ok is not None}

        assert _wait_until(lambda: "bezier/drone1/alive" in alive())
        assert "bezier/drone2/alive" not in alive()
        token.undeclare()
        fake.undeclare()
    finally:
        d1.close()
        d2.close()


def test_observer_reads_but_cannot_command(router: int) -> None:
    d2 = _client(router, "drone2", USERS["drone2"])
    ob = _client(router, "observer", USERS["observer"])
    assert d2 is not None and ob is not None
    try:
        inbound = Listener(d2, "bezier/drone2/command")
        watch = Listener(ob, "bezier/*/status")
        time.sleep(0.3)
        assert _put_until(d2, "bezier/drone2/status", b"s", lambda: watch.has("bezier/drone2/status", b"s"))
        assert not _put_until(ob, "bezier/drone2/command", b"ob-cmd", lambda: inbound.has("bezier/drone2/command",
                                                                                          b"ob-cmd"), timeout=0.6)
    finally:
        d2.close()
        ob.close()


@pytest.mark.parametrize(("user", "password"), [(None, None), ("drone1", "wrong"), ("intruder", "x")])
def test_unauthenticated_clients_are_refused(router: int, user: str | None, password: str | None) -> None:
    s = _client(router, user, password, timeout_ms=500)
    if s is None:
        return  # refused at the handshake
    try:
        got: list[bytes] = []
        sub = s.declare_subscriber("bezier/**", lambda x: got.append(x.payload.to_bytes()))
        op = _client(router, "operator", USERS["operator"])
        assert op is not None
        try:
            _put_until(op, "bezier/drone1/command", b"x", lambda: bool(got), timeout=0.6)
        finally:
            op.close()
        sub.undeclare()
        assert not got
    finally:
        s.close()


def test_a_companion_joins_as_a_client_without_listening(router: int) -> None:
    """`[zenoh] mode = "client"`, `connect`: the companion's session reaches the router and does
    not take the default loopback endpoint (a router may hold it on the same computer)."""
    zc = ZenohConfig(mode="client", connect=(f"tcp/127.0.0.1:{router}",), multicast_scouting=False)
    cfg = zenoh_config(zc)
    assert json.loads(cfg.get_json("listen/endpoints")) in ([], None, {}) or \
        "tcp/127.0.0.1:7447" not in cfg.get_json("listen/endpoints")
    cfg.insert_json5("transport/auth/usrpwd", json.dumps({"user": "drone1", "password": USERS["drone1"]}))
    # a client presenting credentials to its router is not warned about as exposed
    assert exposure(cfg) == []
    session = zenoh.open(cfg)
    session.close()


def test_shipped_fleet_files_load() -> None:
    for path in (SHIPPED, VEHICLE_SHIPPED):
        zenoh.Config.from_file(str(path))
    users = (REPO / "config" / "zenoh-fleet-users.example.txt").read_text().split()
    assert {"drone1", "drone2", "drone3", "operator", "observer"} <= {u.split(":")[0] for u in users}


# -- mutual TLS, as shipped for links that cross a network ---------------------------------------


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


def test_mutual_tls_with_the_shipped_router_configuration(tmp_path: Path) -> None:
    import shutil

    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    d = tmp_path
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-keyout",
             "ca-key.pem", "-out", "ca.pem", "-days", "2", "-subj", "/CN=fleet-ca", "-addext",
             "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=d)
    for name in ("router", "drone1", "operator"):
        _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-keyout",
                 f"{name}-key.pem", "-out", f"{name}.csr", "-subj", f"/CN={name}", cwd=d)
        (d / f"{name}.ext").write_text("subjectAltName=IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
                                       "extendedKeyUsage=serverAuth,clientAuth\n")
        _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca-key.pem", "-CAcreateserial",
                 "-out", f"{name}.pem", "-days", "2", "-extfile", f"{name}.ext", cwd=d)
    users = d / "users.txt"
    users.write_text("".join(f"{u}:{p}\n" for u, p in USERS.items()))
    port = _port()
    cfg = router_config([f"tls/127.0.0.1:{port}"], str(SHIPPED))
    cfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users)))
    cfg.insert_json5("transport/link/tls", json.dumps({
        "root_ca_certificate": str(d / "ca.pem"), "listen_certificate": str(d / "router.pem"),
        "listen_private_key": str(d / "router-key.pem"), "enable_mtls": True}))
    router = zenoh.open(cfg)

    def client(user: str, certificate: bool) -> Any:
        c = zenoh.Config()
        c.insert_json5("mode", '"client"')
        c.insert_json5("connect/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("connect/timeout_ms", "1000")
        c.insert_json5("connect/exit_on_failure", "true")
        tls: dict[str, Any] = {"root_ca_certificate": str(d / "ca.pem")}
        if certificate:
            tls |= {"enable_mtls": True, "connect_certificate": str(d / f"{user}.pem"),
                    "connect_private_key": str(d / f"{user}-key.pem")}
        c.insert_json5("transport/link/tls", json.dumps(tls))
        c.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": USERS[user]}))
        try:
            return zenoh.open(c)
        except zenoh.ZError:
            return None

    try:
        op, d1 = client("operator", True), client("drone1", True)
        assert op is not None and d1 is not None
        try:
            watch = Listener(op, "bezier/**")
            time.sleep(0.3)
            assert _put_until(d1, "bezier/drone1/trajectory", b"tls", lambda: watch.has("bezier/drone1/trajectory",
                                                                                        b"tls"))
            assert not _put_until(d1, "bezier/drone2/trajectory", b"tls-forged",
                                  lambda: watch.has("bezier/drone2/trajectory", b"tls-forged"), timeout=0.6)
        finally:
            op.close()
            d1.close()
        # without a client certificate: no session (the password alone is not enough)
        nocert = client("drone1", False)
        if nocert is not None:
            nocert.close()
        assert nocert is None, "a client without a certificate opened a session"
    finally:
        router.close()


def _send_as(port: int, tmp: Path, user: str) -> subprocess.CompletedProcess[str]:
    conf = tmp / f"{user}.json5"
    conf.write_text(json.dumps({
        "mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": user, "password": USERS[user]}}}}))
    return subprocess.run([sys.executable, "-m", "companion", "send", "command", "-", "--zenoh-config", str(conf),
                           "--vehicle", "drone2", "--wait", "1.5"], input='{"command": "hold"}', cwd=REPO,
                          capture_output=True, text=True, timeout=60, env={**os.environ, "PYTHONPATH": str(REPO)})


def test_send_through_the_router_tells_an_observers_denial(router: int, tmp_path: Path) -> None:
    """Through the secured router, `send` as an observer exits 7 (denied by access control);
    as an operator the (test's silent) companion receives it: 6, not done in time."""
    from companion.cli_client import EXIT_ACCESS_DENIED, EXIT_UNFINISHED

    d2 = _client(router, "drone2", USERS["drone2"])
    assert d2 is not None
    stop = threading.Event()
    inbound = Listener(d2, "bezier/drone2/command")
    pub = d2.declare_publisher("bezier/drone2/status")

    def publish_status() -> None:
        while not stop.is_set():
            pub.put(b'{"state": "IDLE"}')
            time.sleep(0.05)

    th = threading.Thread(target=publish_status, daemon=True)
    th.start()
    try:
        denied = _send_as(router, tmp_path, "observer")
        assert denied.returncode == EXIT_ACCESS_DENIED, denied.stderr
        allowed = _send_as(router, tmp_path, "operator")
        assert allowed.returncode == EXIT_UNFINISHED, allowed.stderr
        assert _wait_until(lambda: inbound.has("bezier/drone2/command", b'{"command": "hold"}'))
    finally:
        stop.set()
        th.join()
        d2.close()
