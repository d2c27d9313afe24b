"""sitl_mock placed in the world (issue 24.2): `--home LAT,LON,ALT`, and GPS_GLOBAL_ORIGIN sent
as PX4 and ArduPilot send it (PX4 once its estimator has a global origin, ~1.5 s after boot;
ArduPilot when its EKF origin is set)."""

from __future__ import annotations

import pytest

from sitl_mock.__main__ import build_parser, main

HOME = (-33.8568, 151.2153, 12.0)


def test_home_option() -> None:
    args = build_parser().parse_args(["--home=-33.8568,151.2153,12"])  # "=": the value starts with "-"
    assert args.home == HOME
    for bad in ("1,2", "a,b,c", "95,0,0", "0,200,0"):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["--home", bad])
    with pytest.raises(SystemExit):
        main(["--home", "1,2"])


def test_px4_sends_its_origin_before_ready_where_it_was_placed(make_mock) -> None:  # type: ignore[no-untyped-def]
    # PX4 SIH (9ececfdd, 5 boots): GPS_GLOBAL_ORIGIN once, 1.4-1.6 s after boot, long before ready
    mock, c = make_mock("px4", speed=4.0, px4_ready_s=30.0, home_lat=HOME[0], home_lon=HOME[1], home_alt=HOME[2])
    origin = c.wait("GPS_GLOBAL_ORIGIN", 3)
    assert origin is not None and not mock.snapshot()["ready"]
    assert (origin.latitude, origin.longitude) == (round(HOME[0] * 1e7), round(HOME[1] * 1e7))
    assert origin.altitude == round((HOME[2] + mock.ground_z) * 1000)  # the local origin: ground_z above


def test_ardupilot_sends_its_origin_when_the_ekf_origin_is_set(make_mock) -> None:  # type: ignore[no-untyped-def]
    _, c = make_mock("ardupilot", speed=4.0, ekf_origin_delay_s=3.0, home_lat=HOME[0], home_lon=HOME[1],
                     home_alt=HOME[2])
    assert c.wait("GPS_GLOBAL_ORIGIN", 0.5) is None
    origin = c.wait("GPS_GLOBAL_ORIGIN", 5)  # unasked: AP_AHRS::set_home sends MSG_HOME and MSG_ORIGIN
    assert origin is not None and origin.latitude == round(HOME[0] * 1e7)
