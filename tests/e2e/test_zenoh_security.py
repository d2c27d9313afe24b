"""The shipped secured Zenoh configuration, end to end with real sessions on loopback.

The companion's session is opened from config/zenoh-companion-secure.json5 exactly as the
service opens it (`zenoh_config` over `[zenoh] config_file`), with only the endpoints (an
explicit tcp/127.0.0.1 port instead of TLS) and the dictionary path swapped for the test.
An operator may command and watch; an observer may only watch; a client without
credentials, or with a wrong password, can do neither.
"""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh

from companion.config import ZenohConfig
from companion.wire.zenoh import exposure, zenoh_config

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "config" / "zenoh-companion-secure.json5"
PREFIX = "bezier/drone1"


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def companion(tmp_path_factory: pytest.TempPathFactory) -> Any:
    tmp = tmp_path_factory.mktemp("zsec")
    users = tmp / "users.txt"
    users.write_text("operator:op-secret\nobserver:obs-secret\n")
    users.chmod(0o600)
    port = _port()
    # The shipped file, as the service loads it; the test's endpoints and dictionary over it.
    text = SHIPPED.read_text()
    conf_path = tmp / "companion.json5"
    conf_path.write_text(text)
    zc = zenoh_config(ZenohConfig(config_file=str(conf_path), listen=(f"tcp/127.0.0.1:{port}",),
                                  multicast_scouting=False))
    zc.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users)))
    zc.insert_json5("transport/link/tls", json.dumps({}))  # TLS is documented, not on loopback
    assert exposure(zc) == []  # authenticated: no warning
    session = zenoh.open(zc)
    got: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def on_sample(sample: Any) -> None:
        with lock:
            got.append((str(sample.key_expr), sample.payload.to_bytes()))

    subs = [session.declare_subscriber(f"{PREFIX}/{k}", on_sample) for k in ("command", "mission", "obstacles", "change")]
    pub = session.declare_publisher(f"{PREFIX}/status")
    stop = threading.Event()

    def publish_status() -> None:
        while not stop.is_set():
            pub.put(b'{"state": "IDLE"}')
            time.sleep(0.05)

    th = threading.Thread(target=publish_status, daemon=True)
    th.start()
    yield {"port": port, "got": got, "lock": lock, "session": session}
    stop.set()
    th.join()
    for s in subs:
        s.undeclare()
    pub.undeclare()
    session.close()


def _client(port: int, user: str | None, password: str | None) -> Any:
    zc = zenoh.Config()
    zc.insert_json5("mode", '"client"')
    zc.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    zc.insert_json5("scouting/multicast/enabled", "false")
    zc.insert_json5("connect/timeout_ms", "2000")
    zc.insert_json5("connect/exit_on_failure", "true")
    if user is not None:
        zc.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
    try:
        return zenoh.open(zc)
    except zenoh.ZError:
        return None  # refused at the handshake: that is a pass for the unauthenticated


def _try(companion: Any, user: str | None, password: str | None, tag: str) -> tuple[bool, bool]:
    """(its command arrived, it saw status) for a client with these credentials."""
    session = _client(companion["port"], user, password)
    if session is None:
        return False, False
    seen: list[bytes] = []
    try:
        sub = session.declare_subscriber(f"{PREFIX}/status", lambda s: seen.append(s.payload.to_bytes()))
        time.sleep(0.5)
        body = json.dumps({"command": "arm", "tag": tag}).encode()
        for _ in range(5):
            session.put(f"{PREFIX}/command", body)
            session.put(f"{PREFIX}/mission", body)
            time.sleep(0.1)
        time.sleep(0.5)
        sub.undeclare()
    finally:
        session.close()
    with companion["lock"]:
        arrived = any(tag.encode() in p for _, p in companion["got"])
    return arrived, bool(seen)


def test_operator_commands_and_watches(companion: Any) -> None:
    assert _try(companion, "operator", "op-secret", "op-1") == (True, True)


def test_operator_cannot_fake_what_the_companion_publishes(companion: Any) -> None:
    """Issue 21.2: an operator's put on `events` or `status` does not pass the companion's
    access control (the operator's rights to put are on the four inbound keys only)."""
    seen: list[bytes] = []
    sub = companion["session"].declare_subscriber(f"{PREFIX}/events", lambda s: seen.append(s.payload.to_bytes()))
    session = _client(companion["port"], "operator", "op-secret")
    assert session is not None
    try:
        time.sleep(0.5)
        for _ in range(5):
            session.put(f"{PREFIX}/events", b'{"type": "completed", "key": "command", "fake": true}')
            time.sleep(0.1)
        time.sleep(0.5)
    finally:
        session.close()
        sub.undeclare()
    assert not seen


def test_observer_watches_but_cannot_command(companion: Any) -> None:
    assert _try(companion, "observer", "obs-secret", "obs-1") == (False, True)


@pytest.mark.parametrize(("user", "password"), [(None, None), ("operator", "wrong"), ("intruder", "x")])
def test_unauthenticated_client_can_do_nothing(companion: Any, user: str | None, password: str | None) -> None:
    assert _try(companion, user, password, f"anon-{user}-{password}") == (False, False)


def test_default_listens_on_loopback_only_and_warns_otherwise() -> None:
    assert ZenohConfig().listen == ("tcp/127.0.0.1:7447",)
    assert exposure(zenoh_config(ZenohConfig())) == []
    why = exposure(zenoh_config(ZenohConfig(listen=("tcp/0.0.0.0:7447",))))
    assert why == ["listening on tcp/0.0.0.0:7447"]
    assert exposure(zenoh_config(ZenohConfig(connect=("tcp/10.0.0.2:7447",))))


# -- TLS (mutual), as shipped for links that cross a network ------------------------------------


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True)


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    d = tmp_path_factory.mktemp("pki")
    _openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca-key.pem", "-out", "ca.pem",
             "-days", "2", "-subj", "/CN=test-ca", "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign", cwd=d)
    for name in ("companion", "operator"):
        _openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}-key.pem", "-out", f"{name}.csr",
                 "-subj", f"/CN={name}", cwd=d)
        (d / f"{name}.ext").write_text("subjectAltName=IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
                                       "extendedKeyUsage=serverAuth,clientAuth\n")
        _openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca-key.pem",
                 "-CAcreateserial", "-out", f"{name}.pem", "-days", "2", "-extfile", f"{name}.ext", cwd=d)
    return d


def test_tls_with_client_certificates_and_passwords(pki: Path) -> None:
    users = pki / "users.txt"
    users.write_text("operator:op-secret\n")
    port = _port()
    zc = zenoh_config(ZenohConfig(config_file=str(SHIPPED), listen=(f"tls/127.0.0.1:{port}",),
                                  multicast_scouting=False))
    zc.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(users)))
    zc.insert_json5("transport/link/tls", json.dumps({
        "root_ca_certificate": str(pki / "ca.pem"), "listen_certificate": str(pki / "companion.pem"),
        "listen_private_key": str(pki / "companion-key.pem"), "enable_mtls": True}))
    session = zenoh.open(zc)
    got: list[bytes] = []
    sub = session.declare_subscriber(f"{PREFIX}/command", lambda s: got.append(s.payload.to_bytes()))

    def attempt(tag: str, certificate: bool, password: str | None) -> bool:
        c = zenoh.Config()
        c.insert_json5("mode", '"client"')
        c.insert_json5("connect/endpoints", json.dumps([f"tls/127.0.0.1:{port}"]))
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("connect/timeout_ms", "2000")
        c.insert_json5("connect/exit_on_failure", "true")
        tls: dict[str, Any] = {"root_ca_certificate": str(pki / "ca.pem")}
        if certificate:
            tls |= {"enable_mtls": True, "connect_certificate": str(pki / "operator.pem"),
                    "connect_private_key": str(pki / "operator-key.pem")}
        c.insert_json5("transport/link/tls", json.dumps(tls))
        if password is not None:
            c.insert_json5("transport/auth/usrpwd", json.dumps({"user": "operator", "password": password}))
        try:
            client = zenoh.open(c)
        except zenoh.ZError:
            return False
        try:
            time.sleep(0.3)
            for _ in range(3):
                client.put(f"{PREFIX}/command", tag.encode())
                time.sleep(0.1)
            time.sleep(0.3)
        finally:
            client.close()
        return tag.encode() in got

    try:
        assert attempt("ok", certificate=True, password="op-secret")
        assert not attempt("no-cert", certificate=False, password="op-secret")
        assert not attempt("no-password", certificate=True, password=None)
    finally:
        sub.undeclare()
        session.close()


def test_shipped_files_load() -> None:
    for name in ("zenoh-companion-secure.json5", "zenoh-operator.json5"):
        zenoh.Config.from_file(str(REPO / "config" / name))
    users = (REPO / "config" / "zenoh-users.example.txt").read_text().split()
    assert [u.split(":")[0] for u in users] == ["operator", "observer"]


# -- `send` tells an access-control denial apart (issue 20.7) ------------------------------------


def _send_as(companion: Any, tmp_path: Path, user: str, password: str) -> subprocess.CompletedProcess[str]:
    conf = tmp_path / f"{user}.json5"
    conf.write_text(json.dumps({
        "mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{companion['port']}"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": user, "password": password}}}}))
    import sys

    return subprocess.run([sys.executable, "-m", "companion", "send", "command", "-", "--zenoh-config", str(conf),
                           "--vehicle", "drone1", "--wait", "2"], input='{"command": "hold"}', cwd=REPO,
                          capture_output=True, text=True, timeout=60)


def test_send_reports_an_observers_command_as_denied(companion: Any, tmp_path: Path) -> None:
    from companion.cli_client import EXIT_ACCESS_DENIED, EXIT_UNFINISHED

    denied = _send_as(companion, tmp_path, "observer", "obs-secret")
    assert denied.returncode == EXIT_ACCESS_DENIED, denied.stderr
    assert "denied" in denied.stderr and "access control" in denied.stderr
    # an operator's command reaches the (test's) companion, which says nothing: not a denial
    allowed = _send_as(companion, tmp_path, "operator", "op-secret")
    assert allowed.returncode == EXIT_UNFINISHED, allowed.stderr
