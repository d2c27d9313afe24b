"""The PX4 flavour's boot as PX4 SIH boots (9ececfdd, 5 boots, measured 2026-12-03), with pymavlink
as the client: the local estimate on the ground drifts tens of metres horizontally until PX4 is
ready, then is reset to where the vehicle stands; GPS_GLOBAL_ORIGIN comes once, ~1.5 s after
boot, long before ready (and on request); the arming-check report names the vertical-velocity
estimator check."""

from __future__ import annotations

import itertools
import math
import struct
import time
from typing import Any

from pymavlink.dialects.v20 import common as mav

from sitl_mock import events as px4_events
from sitl_mock import px4

READY = 10.0  # s of simulated time to ready, for the test (PX4: ~36.5)


def _since_boot(msg: Any) -> float:
    return float(msg.time_boot_ms) / 1000.0


def test_estimate_drifts_horizontally_until_ready_then_is_reset(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("px4", speed=4.0, px4_ready_s=READY)
    truth = mock.snapshot()["position"]
    before: list[Any] = []
    after: list[Any] = []
    end = time.monotonic() + 2 * READY / 4.0 + 5.0
    while time.monotonic() < end and len(after) < 30:
        m = c.wait("LOCAL_POSITION_NED", 1.0)
        if m is None:
            continue
        (before if _since_boot(m) < READY else after).append(m)
    assert before and len(after) >= 30, (len(before), len(after))
    assert mock.snapshot()["ready"] and not mock.snapshot()["armed"]
    # the vehicle itself never moved
    assert math.dist(mock.snapshot()["position"], truth) < 1e-9

    def off(m: Any) -> float:
        return math.hypot(m.x - truth[0], m.y - truth[1])

    drift = [off(m) for m in before]
    # from where the vehicle stands, away smoothly, to the measured size by ready (23-42 m)
    assert drift[0] < 1.0, drift[:3]
    assert all(b >= a - 1e-6 for a, b in itertools.pairwise(drift)), "the drift is not smooth"
    last = before[-1]
    assert _since_boot(last) > READY - 0.5 and 23.0 <= off(last) <= 42.0, (_since_boot(last), off(last))
    # its velocity says the same (the estimator believes the vehicle moves)
    speed = math.hypot(last.vx, last.vy)
    assert speed > 1.0, speed
    # z wanders on the ground over the measured band (-0.94 to +3.60 on PX4's +1.6 ground)
    zs = [m.z for m in before]
    assert min(zs) >= -0.94 - 1e-6 and max(zs) <= 3.60 + 1e-6 and max(zs) - min(zs) > 0.5, (min(zs), max(zs))
    # ready: reset to where the vehicle stands, at rest, and home set there
    for m in after:
        assert math.dist((m.x, m.y, m.z), truth) < 1e-6 and math.hypot(m.vx, m.vy, m.vz) < 1e-6, m
    home = c.wait("HOME_POSITION", 5, lambda h: (h.x, h.y, h.z) != (0.0, 0.0, 0.0))
    assert home is not None and math.dist((home.x, home.y, home.z), truth) < 1e-4


def test_drift_size_is_configurable_and_validated(make_mock) -> None:  # type: ignore[no-untyped-def]
    import pytest

    from sitl_mock import MockAutopilot, MockConfig
    from sitl_mock.__main__ import build_parser

    assert 23.0 <= px4.DRIFT_XY_M <= 42.0
    assert build_parser().parse_args(["--px4-drift", "0"]).px4_drift_m == 0.0
    with pytest.raises(ValueError, match="px4_drift_m"):
        MockAutopilot(MockConfig(px4_drift_m=-1.0))
    mock, c = make_mock("px4", speed=4.0, px4_ready_s=READY, px4_drift_m=0.0)
    truth = mock.snapshot()["position"]
    xs = [(m.x, m.y) for m in c.collect(1.0) if m.get_type() == "LOCAL_POSITION_NED"]
    assert xs and all(math.hypot(x - truth[0], y - truth[1]) < 1e-9 for x, y in xs)


def test_gps_global_origin_comes_once_early_and_on_request(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("px4", speed=2.0, px4_ready_s=60.0)
    # from connecting (well before 1.5 s) to 16 s of simulated time: more than the 10 s period
    # at which a stream at the mock's default rate (0.1 Hz) would have sent it again
    seen = c.collect(8.0)
    origins = [m for m in seen if m.get_type() == "GPS_GLOBAL_ORIGIN"]
    assert mock.t - mock.boot_t > 12.0
    assert len(origins) == 1, [m.time_usec for m in origins]
    at = origins[0].time_usec / 1e6
    assert 1.4 <= at <= 1.6, at  # measured 1.4-1.6 s after boot
    assert origins[0].latitude == round(mock.config.home_lat * 1e7)
    # PX4 is not ready: home still at the local origin, while the origin is known
    homes = [m for m in seen if m.get_type() == "HOME_POSITION"]
    assert homes and all((h.x, h.y, h.z) == (0.0, 0.0, 0.0) for h in homes)
    assert not mock.snapshot()["ready"]
    # asked for, it is sent (PX4's stream answers REQUEST_MESSAGE whenever it has an origin)
    result, before_ack = c.command_collect(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)
    assert result == mav.MAV_RESULT_ACCEPTED
    got = [m for m in before_ack if m.get_type() == "GPS_GLOBAL_ORIGIN"] or [c.wait("GPS_GLOBAL_ORIGIN", 1.0)]
    assert got[0] is not None and got[0].latitude == origins[0].latitude


def test_gps_global_origin_again_after_a_reboot(make_mock) -> None:  # type: ignore[no-untyped-def]
    """The origin is new once per boot: a rebooted PX4 sends it again, ~1.5 s after that boot."""
    mock, c = make_mock("px4", speed=2.0, px4_ready_s=60.0, control="127.0.0.1:0")
    assert c.wait("GPS_GLOBAL_ORIGIN", 3.0) is not None
    from sitl_mock import ControlClient

    assert mock.control_address is not None
    with ControlClient(*mock.control_address) as ctl:
        assert ctl.reboot()["ok"]
    c.drain()
    again = c.wait("GPS_GLOBAL_ORIGIN", 6.0)
    assert again is not None and 1.4 <= again.time_usec / 1e6 <= 1.6, again


def test_boot_report_names_the_vertical_velocity_check(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("px4", speed=4.0, px4_ready_s=60.0, px4_report_every_s=4.0)
    vert = px4_events.IDS["check_estimator_vert_vel_not_stable"]
    seen = c.collect(4.0, until=lambda m: m.get_type() == "EVENT" and int(m.id) == vert)
    ids = [int(m.id) for m in seen if m.get_type() == "EVENT"]
    assert vert == 25948424 and vert in ids, ids  # PX4's id, as measured
    assert px4_events.IDS["check_estimator_hor_vel_not_stable"] not in ids
    ev = next(m for m in seen if m.get_type() == "EVENT" and int(m.id) == vert)
    modes, component = struct.unpack_from("<IB", bytes(ev.arguments).ljust(40, b"\0"))
    assert component == px4_events.HEALTH_INDEX["local_position_estimate"]
    assert modes & (1 << px4_events.NAV_STATE["offboard"])
    # the refused arm itself carries only commander_arm_denied_resolve_failures, as before
    result, at_arm = c.command_collect(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert result == mav.MAV_RESULT_TEMPORARILY_REJECTED and not mock.snapshot()["armed"]
    assert px4_events.IDS["commander_arm_denied_resolve_failures"] in [int(m.id) for m in at_arm
                                                                       if m.get_type() == "EVENT"]
