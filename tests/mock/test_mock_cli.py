"""``python -m sitl_mock`` as a process: endpoints, control socket, signals, bad input."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mockkit import Client, free_tcp_port, free_udp_port
from pymavlink import mavutil

from sitl_mock import ControlClient, read_log


def start(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "sitl_mock", *args], stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def wait_ready(proc: subprocess.Popen[str]) -> str:
    assert proc.stderr is not None
    line = proc.stderr.readline()
    assert "sitl_mock" in line, line
    return line


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_process_serves_udp_tcp_control_and_stops_cleanly(tmp_path: Path, sig: signal.Signals) -> None:
    udp, tcp, ctl = free_udp_port(), free_tcp_port(), free_tcp_port()
    log = tmp_path / "flight.jsonl"
    proc = start("--autopilot", "ardupilot", "--endpoint", f"udpin:127.0.0.1:{udp}", "--endpoint",
                 f"tcpin:127.0.0.1:{tcp}", "--control", f"127.0.0.1:{ctl}", "--log", str(log),
                 "--sysid", "7", "--speed", "2")
    try:
        wait_ready(proc)
        client = Client(udp)
        assert client.hello().get_srcSystem() == 7
        client.close()
        conn = mavutil.mavlink_connection(f"tcp:127.0.0.1:{tcp}", dialect="common")
        hb = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=3)
        assert hb is not None and mavutil.mode_string_v10(hb) == "STABILIZE"
        conn.close()
        with ControlClient("127.0.0.1", ctl) as c:
            assert c.set_mode("LOITER")["mode"] == "LOITER"
        time.sleep(0.2)
        proc.send_signal(sig)
        assert proc.wait(timeout=5) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    records = read_log(log)
    assert records[-1] == {"type": "event", "t": records[-1]["t"], "event": "stopped"}
    assert any(r["type"] == "mode" and r["to"] == "LOITER" and r["reason"] == "pilot" for r in records)
    assert any(r["type"] == "state" for r in records)


def test_control_stop_ends_process(tmp_path: Path) -> None:
    ctl = free_tcp_port()
    proc = start("--endpoint", f"udpin:127.0.0.1:{free_udp_port()}", "--control", f"127.0.0.1:{ctl}",
                 "--log", str(tmp_path / "f.jsonl"))
    try:
        wait_ready(proc)
        with ControlClient("127.0.0.1", ctl) as c:
            assert c.stop()["ok"]
        assert proc.wait(timeout=5) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    assert read_log(tmp_path / "f.jsonl")[-1]["event"] == "stopped"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--endpoint", "serial:/dev/ttyS0"], "--endpoint: expected udpin:HOST:PORT"),
        (["--fault", "drop=1.5"], "drop: fraction must be in [0, 1]"),
        (["--sysid", "0"], "sysid: must be in 1..255"),
        (["--param", "NOPE=1"], "params: unknown parameter 'NOPE'"),
        (["--takeover-at", "5:GUIDED"], "takeovers[0]: mode: unknown px4 mode 'GUIDED'"),
    ],
)
def test_bad_arguments_are_named(args: list[str], message: str) -> None:
    out = subprocess.run([sys.executable, "-m", "sitl_mock", *args], capture_output=True, text=True, timeout=20)
    assert out.returncode == 2 and message in out.stderr
