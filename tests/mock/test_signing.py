"""MAVLink 2 signing: the mock, given a key, ignores unsigned or wrongly signed commands and
setpoints (and says so in its log); the companion, given the key file, signs and is obeyed."""

from __future__ import annotations

import asyncio
import os
import time
from pathlib import Path

from companionkit import service_for, serving, until
from mockkit import Client, records, wait_for
from pymavlink.dialects.v20 import common as mav

from sitl_mock import MockAutopilot, MockConfig

KEY = bytes(range(32))


def _mock(tmp_path: Path) -> MockAutopilot:
    return MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], signing_key=KEY,
                                    log_path=str(tmp_path / "f.jsonl"))).start()


def _ack(c: Client, timeout: float = 1.0) -> object:
    c.drain()
    c.mav.command_long_send(1, 1, mav.MAV_CMD_REQUEST_MESSAGE, 0, mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                            0, 0, 0, 0, 0, 0)
    return c.wait("COMMAND_ACK", timeout, lambda m: m.command == mav.MAV_CMD_REQUEST_MESSAGE)


def test_mock_ignores_unsigned_and_wrongly_signed_commands(tmp_path: Path) -> None:
    mock = _mock(tmp_path)
    c = Client(mock.addresses[0][1])
    try:
        c.hello()  # an unsigned heartbeat is still heard (the mock answers it)
        assert _ack(c) is None  # unsigned command: ignored
        for _ in range(5):
            c.setpoint(0.0, 0.0, -2.0)  # unsigned setpoints: ignored, not even logged as received
        time.sleep(0.2)
        assert not records(mock, "setpoint")
        c.conn.setup_signing(os.urandom(32), sign_outgoing=True, allow_unsigned_callback=lambda *_: True)
        assert _ack(c) is None  # wrong key: ignored
        c.conn.setup_signing(KEY, sign_outgoing=True, allow_unsigned_callback=lambda *_: True)
        assert _ack(c) is not None  # the right key: obeyed
        c.setpoint(0.0, 0.0, -2.0)
        assert wait_for(lambda: records(mock, "setpoint"))
        assert wait_for(lambda: [r for r in records(mock, "event") if r.get("event") == "signature_rejected"])
    finally:
        c.close()
        mock.stop()


def test_companion_signs_with_its_key_file(tmp_path: Path) -> None:
    key_file = tmp_path / "mavlink.key"
    key_file.write_text(KEY.hex() + "\n")
    mock = _mock(tmp_path)

    async def go() -> None:
        svc = service_for(mock, mavlink={"signing_key_file": str(key_file)})
        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 10, "position")
            await svc.commands.arm()  # OFFBOARD (signed setpoints for 1.1 s), then arm
            assert mock.snapshot()["armed"] and mock.snapshot()["mode"] == "OFFBOARD"

    try:
        asyncio.run(go())
        time.sleep(0.6)
        assert not [r for r in records(mock, "event") if r.get("event") == "signature_rejected"]
    finally:
        mock.stop()
