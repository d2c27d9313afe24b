"""`watch --wait-for`: what each word waits for."""

from __future__ import annotations


def test_wait_for_ready_needs_home_and_a_position() -> None:
    """`watch --wait-for ready` (README walkthrough, demo): real ArduCopter reports home ~22 s
    before its first LOCAL_POSITION_NED, and `start` is refused without a position."""
    from companion.cli_watch import status_reached

    assert not status_reached({"home": [0.0, 0.0, 0.0], "position_ok": False}, "ready")
    assert status_reached({"home": [0.0, 0.0, 0.0], "position_ok": False}, "home")
    assert not status_reached({"home": None, "position_ok": True}, "ready")
    assert status_reached({"home": [0.0, 0.0, 0.0], "position_ok": True}, "ready")
