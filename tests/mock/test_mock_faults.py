"""Faults (drop, latency, pause, reboot, arming rejection), the control socket and takeover."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest
from mockkit import CUSTOM, POS_ONLY, Streamer, free_tcp_port, records, wait_for
from pymavlink.dialects.v20 import common as mav

from sitl_mock import ControlClient, FaultSpec


def test_drop_fraction_roughly_honoured(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("px4", speed=4.0, faults=FaultSpec(drop=0.4), seed=3)
    c.drain()
    got = []
    end = time.monotonic() + 1.5
    while time.monotonic() < end:
        m = c.wait("LOCAL_POSITION_NED", 0.3)
        if m is not None:
            got.append(m.time_boot_ms)
    span_s = (got[-1] - got[0]) / 1000.0
    expected = span_s * 30.0  # LOCAL_POSITION_NED at 30 Hz of simulated time
    assert len(got) / expected == pytest.approx(0.6, abs=0.1)
    out = mock.link_faults
    assert out.dropped["out"] / (out.dropped["out"] + out.passed["out"]) == pytest.approx(0.4, abs=0.05)


def test_latency_delays_replies(make_mock) -> None:  # type: ignore[no-untyped-def]
    _mock, c = make_mock("px4", speed=1.0, faults=FaultSpec(latency_s=0.15))
    t0 = time.monotonic()
    assert c.command(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_HOME_POSITION) == mav.MAV_RESULT_ACCEPTED
    assert time.monotonic() - t0 >= 0.29  # 150 ms in, 150 ms out


def test_pause_stops_heartbeats(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("px4", speed=4.0, faults=FaultSpec(pauses=[(2.0, 3.0)]))
    stamps = []
    end = time.monotonic() + 3.0
    while time.monotonic() < end:
        m = c.wait("LOCAL_POSITION_NED", 0.3)
        if m is not None:
            stamps.append(m.time_boot_ms / 1000.0)
    gaps = [b - a for a, b in itertools.pairwise(stamps)]
    assert max(gaps) == pytest.approx(3.0, abs=0.1)
    paused = [r for r in records(mock, "event") if r["event"] == "link_paused"]
    assert paused[0]["t"] == pytest.approx(2.0, abs=0.01)


def test_control_socket_pause_reboot_state(make_mock) -> None:  # type: ignore[no-untyped-def]
    port = free_tcp_port()
    mock, c = make_mock("px4", speed=2.0, control=f"127.0.0.1:{port}")
    with ControlClient("127.0.0.1", port) as ctl:
        state = ctl.state()
        assert state["ok"] and state["mode"] == "LOITER" and not state["armed"] and state["landed"]
        ground = state["ground_z"]
        assert c.command(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, float("nan")) == mav.MAV_RESULT_ACCEPTED
        assert c.command(400, 1) == mav.MAV_RESULT_ACCEPTED
        assert wait_for(lambda: ctl.state()["position"][2] < ground - 2.0, 5)
        # Pause: no heartbeat for the pause duration.
        assert ctl.pause_link(1.0)["ok"]
        c.drain()
        t0 = time.monotonic()
        assert c.wait("HEARTBEAT", 0.4) is None
        assert c.wait("HEARTBEAT", 3.0) is not None and time.monotonic() - t0 >= 0.45
        # Reboot: silence, then disarmed, landed at home, boot time restarted.
        before = c.wait("LOCAL_POSITION_NED").time_boot_ms
        assert ctl.reboot()["ok"]
        st = ctl.state()
        assert st["rebooting"] and not st["armed"] and st["position"] == [0.0, 0.0, ground]
        c.drain()
        assert c.wait("HEARTBEAT", 1.0) is None
        hb = c.wait("HEARTBEAT", 3.0)
        assert hb is not None and not hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
        assert c.wait("LOCAL_POSITION_NED").time_boot_ms < min(before, 500)
        # Errors are specific.
        bad = ctl.request("set_mode", mode="GUIDED")
        assert not bad["ok"] and "unknown px4 mode 'GUIDED'" in bad["error"]
        assert "unknown command" in ctl.request("fly")["error"]
        assert "'fraction' must be a number" in ctl.request("drop", fraction="lots")["error"]
        assert ctl.drop(0.0)["ok"] and ctl.latency(0)["ok"]
        assert ctl.reject_arming(True)["ok"]
        assert c.command(400, 1) == mav.MAV_RESULT_TEMPORARILY_REJECTED
    assert any(r["event"] == "reboot" for r in records(mock, "event"))


def test_reject_arming_fault(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("px4", speed=4.0, faults=FaultSpec(reject_arming=True))
    assert c.command(400, 1) == mav.MAV_RESULT_TEMPORARILY_REJECTED  # as PX4 answers a denied arming
    assert not mock.snapshot()["armed"]
    status = c.wait("SYS_STATUS")
    assert not status.onboard_control_sensors_health & mav.MAV_SYS_STATUS_PREARM_CHECK
    assert any("Arming denied" in r.get("text", "") for r in records(mock, "event"))


def test_pilot_takeover_from_command_line_schedule(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("px4", speed=2.0, takeovers=[(4.0, "POSCTL")])
    with Streamer(mock.addresses[0][1], x=0.0, y=0.0, z=-2.0, mask=POS_ONLY):
        assert wait_for(lambda: mock.snapshot()["t"] > 1.5, 3)
        assert c.command(176, CUSTOM, 6, 0) == mav.MAV_RESULT_ACCEPTED
        assert c.command(400, 1) == mav.MAV_RESULT_ACCEPTED
        assert wait_for(lambda: mock.snapshot()["mode"] == "POSCTL", 5)
    change = [r for r in records(mock, "mode") if r["to"] == "POSCTL"]
    assert change[-1]["reason"] == "pilot" and change[-1]["t"] == pytest.approx(4.0, abs=0.01)


def test_sensor_noise_on_reported_position_only(make_mock) -> None:  # type: ignore[no-untyped-def]
    def samples(seed: int) -> list[float]:
        mock, c = make_mock("px4", speed=4.0, noise=0.05, seed=seed)  # seeded: reproducible draws
        c.drain()
        out = [c.wait("LOCAL_POSITION_NED").x for _ in range(20)]
        assert mock.snapshot()["position"][0] == 0.0  # the truth stays put; only reports are noisy
        return out

    a = samples(1)
    assert 0.01 < float(np.std(a)) < 0.15
