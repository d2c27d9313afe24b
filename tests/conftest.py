"""Session set-up shared by every test directory."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _px4_mock_ready_at_boot(monkeypatch: pytest.MonkeyPatch) -> None:
    """In-process PX4 mocks are ready to arm at boot unless a test sets `px4_ready_s`: PX4's
    ~36 s estimator settling (sitl_mock.px4) is the subject of its own tests, not of every
    test that arms."""
    from sitl_mock import px4

    monkeypatch.setattr(px4, "DEFAULT_READY_S", 0.0)


@pytest.fixture(autouse=True)
def _ardupilot_mock_origin_at_boot(monkeypatch: pytest.MonkeyPatch) -> None:
    """In-process ArduPilot mocks set their EKF origin at boot unless a test asks for another
    delay than the stock one: ArduCopter's ~40 s wait (sitl_mock.ardupilot) is the subject of
    test_mock_ardupilot_strict.py, which sets its delays, not of every test that flies."""
    from sitl_mock import server

    stock = server.MockConfig()
    rules = server.ArduPilotRules

    def fast(rc_throttle: int | None, ekf_origin_delay_s: float, spool_up_s: float, shaping: bool,
             position_after_origin_s: float = 0.0,
             home_shift_at_arming: tuple[float, float] = (0.0, 0.0)) -> object:
        origin = 0.0 if ekf_origin_delay_s == stock.ekf_origin_delay_s else ekf_origin_delay_s
        position = 0.0 if position_after_origin_s == stock.position_after_origin_s else position_after_origin_s
        # the home shift costs no time: every flight keeps it, as stock ArduCopter does
        return rules(rc_throttle, origin, spool_up_s, shaping, position, home_shift_at_arming)

    monkeypatch.setattr(server, "ArduPilotRules", fast)


@pytest.fixture(autouse=True)
def _px4_mock_on_the_calibrated_response(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """In-process PX4 mocks respond as the calibrated (ArduCopter-like, ~60 ms) vehicle unless a
    test gives its own: the companion's flights were written against it, and PX4 SIH's 0.3 s lag
    (sitl_mock's PX4 default, `px4_sih`) is the subject of its own tests (the response's, the lag
    estimate's), not of every test that flies. The CLI mock and the e2e rigs say what they fly."""
    if request.node.module.__name__.endswith("test_mock_px4_response"):
        return
    from sitl_mock import server

    monkeypatch.setitem(server.DEFAULT_RESPONSE, "px4", "calibrated")


@pytest.fixture(scope="session", autouse=True)
def _compiled_planner_kernel() -> None:
    """Compile the planner's numba kernel once, here, into its on-disk cache: the companion's
    worker processes started by later tests then load it (~0.3 s) instead of each compiling it
    (~20 s) in the middle of a timed flight."""
    from planner_core.iterative import warm_up

    warm_up()


# Run alone (`make test`'s second pass, without pytest-xdist's workers beside them): what they
# measure is the machine's own timing or memory under a load they make themselves (a CPU hog,
# a burst, a soak); another flight beside them would be a load nobody chose. Every other test
# runs two at a time (`-n 2`): a flight spends most of its time waiting on the simulated clock.
SERIAL = {
    "test_memory_soak",  # the main process's RSS
    "test_missions_in_flight",  # planning time against split times, with and without a hog
    "test_fuzz_live",  # setpoint gaps under a flood of hostile messages
    "test_lag_settles",  # the lag estimate's convergence in ms
    "test_lead",  # tracking error with and without the auto lead
    "test_setpoint_process",  # setpoint gaps while the loop holds the GIL
    "test_inbound_burst",  # admitted rate of a 5,000-message burst
    "test_live",  # the Foxglove view's deliveries within their timeouts
}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.module is not None and item.module.__name__.rsplit(".", 1)[-1] in SERIAL:
            item.add_marker(pytest.mark.serial)
