"""A client we did not write: MAVSDK (native 4.x binding) flies the PX4 flavour in OFFBOARD."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from mockkit import free_udp_port

from sitl_mock import MockAutopilot, MockConfig, read_log

mavsdk = pytest.importorskip("mavsdk", reason="mavsdk (MAVSDK-Python) is not installed")
try:
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.action import Action
    from mavsdk.plugins.offboard import AccelerationNed, Offboard, PositionNedYaw, VelocityNedYaw
    from mavsdk.plugins.telemetry import Telemetry
except (ImportError, OSError) as exc:  # e.g. libcmavsdk.so cannot load on this machine
    pytest.skip(f"MAVSDK native binding unusable: {exc}", allow_module_level=True)


def test_mavsdk_connects_arms_and_flies_offboard(tmp_path: Path) -> None:
    port = free_udp_port()
    log = tmp_path / "mavsdk.jsonl"
    # MAVSDK's udpin:// listens, so the mock sends to it (udpout).
    cfg = MockConfig(autopilot="px4", endpoints=[f"udpout:127.0.0.1:{port}"], log_path=str(log),
                     log_rate_hz=50.0, speed=2.0)
    mock = MockAutopilot(cfg).start()
    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = sdk.first_autopilot(10.0)
        assert system is not None and system.is_connected()
        telemetry, action, offboard = Telemetry(system), Action(system), Offboard(system)
        deadline = time.monotonic() + 10.0
        health = telemetry.health()
        while time.monotonic() < deadline and not (
            health.is_local_position_ok and health.is_global_position_ok and health.is_home_position_ok
            and health.is_armable
        ):
            time.sleep(0.2)
            health = telemetry.health()
        assert health.is_local_position_ok and health.is_global_position_ok and health.is_home_position_ok
        assert health.is_armable

        action.arm()
        offboard.set_position_velocity_acceleration_ned(
            PositionNedYaw(0.0, 0.0, -2.0, 0.0), VelocityNedYaw(0.0, 0.0, 0.0, 0.0),
            AccelerationNed(0.0, 0.0, 0.0),
        )
        # MAVSDK now streams the setpoint at 20 Hz; PX4 wants a stream before OFFBOARD.
        time.sleep(0.8)
        offboard.start()
        offboard.set_position_ned(PositionNedYaw(3.0, 1.0, -2.5, 0.0))
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            p = mock.snapshot()["position"]
            if abs(p[0] - 3.0) < 0.05 and abs(p[1] - 1.0) < 0.05 and abs(p[2] + 2.5) < 0.05:
                break
            time.sleep(0.1)
        pv = telemetry.position_velocity_ned()
        assert abs(pv.position.north_m - 3.0) < 0.2 and abs(pv.position.down_m + 2.5) < 0.2
        offboard.stop()
    finally:
        sdk.destroy()
        mock.stop()

    records = read_log(log)
    states = [r for r in records if r["type"] == "state"]
    final = states[-1]["pos"]
    assert abs(final[0] - 3.0) < 0.1 and abs(final[1] - 1.0) < 0.1 and abs(final[2] + 2.5) < 0.1
    assert any(r["type"] == "mode" and r["to"] == "OFFBOARD" for r in records)
    setpoints = [r for r in records if r["type"] == "setpoint"]
    assert setpoints and all(r["valid"] for r in setpoints)  # MAVSDK follows PX4's rules
    assert any(r["applied"] and r["pos"] == [3.0, 1.0, -2.5] for r in setpoints)
