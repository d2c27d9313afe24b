"""Two callers of one MAVLink command at once. COMMAND_ACK names only the command, so the link
sends the second only after the first's answer: both get their own ACK. (Found in CI: the
link-up's HOME_POSITION request after a re-bind cancelled a caller's request of the same
command, which then saw CancelledError instead of an answer.)"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

from companionkit import service_for, serving, until
from mockkit import free_udp_port

from companion.wire.mavlink import mavlink
from sitl_mock import MockAutopilot, MockConfig
from sitl_mock.vehicle import RESPONSES


def test_concurrent_requests_of_one_command_each_get_an_answer(tmp_path: Path) -> None:
    port = free_udp_port()
    log_path = tmp_path / "mock.jsonl"
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=[f"udpout:127.0.0.1:{port}"],
                                    log_path=str(log_path), vehicle=RESPONSES["calibrated"])).start()
    results: list[Any] = []

    async def go() -> None:
        svc = service_for(mock, mavlink={"url": f"udpin:127.0.0.1:{port}"})
        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 10, "position")
            results.extend(await asyncio.gather(
                svc.link.request_home(), svc.link.request_origin(), svc.link.request_home(),
                svc.link.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION),
                return_exceptions=True))

    try:
        asyncio.run(go())
    finally:
        mock.stop()
    assert results[:3] == [None, None, None], results
    assert results[3] == mavlink.MAV_RESULT_ACCEPTED, results
    log = [json.loads(x) for x in log_path.read_text().splitlines() if x.strip()]
    asked = [r["params"][0] for r in log if r.get("event") == "command"
             and r.get("command") == mavlink.MAV_CMD_REQUEST_MESSAGE]
    # each request reached the autopilot (none was dropped for another of its kind)
    for msg_id, n in ((mavlink.MAVLINK_MSG_ID_HOME_POSITION, 2), (mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, 1),
                      (mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 1)):
        assert asked.count(msg_id) >= n, (msg_id, asked)
