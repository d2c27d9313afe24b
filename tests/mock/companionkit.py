"""The companion's Service in process against an in-process mock (no subprocesses)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import time
from collections.abc import AsyncIterator, Callable
from typing import Any

import zenoh

from companion.config import config_from_dict
from companion.service import Service
from sitl_mock import MockAutopilot


def zenoh_client(svc: Service | int) -> Any:
    """A Zenoh client session on loopback to the in-process service's listen endpoint (or a
    port), scouting off: an operator, or another vehicle."""
    port = svc if isinstance(svc, int) else int(svc.cfg.zenoh.listen[0].rsplit(":", 1)[1])
    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    c.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(c)


def free_tcp() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def service_for(mock: MockAutopilot, **sections: dict[str, Any]) -> Service:
    port = mock.addresses[0][1]
    table: dict[str, Any] = {
        "vehicle": {"id": "inproc"},
        "mavlink": {"url": f"udpout:127.0.0.1:{port}"},
        "zenoh": {"listen": [f"tcp/127.0.0.1:{free_tcp()}"], "multicast_scouting": False},
        "planner": {"executor": "thread"},
        "safety": {"takeoff_altitude": 1.0},
    }
    for name, values in sections.items():
        table[name] = {**table.get(name, {}), **values}
    return Service(config_from_dict(table))


class Events:
    """Every event the service reports, as published."""

    def __init__(self, svc: Service) -> None:
        self.all: list[dict[str, Any]] = []
        publish = svc.report.publish

        def capture(key: str, body: dict[str, Any]) -> None:
            if key == "events":
                self.all.append(body)
            if publish is not None:
                publish(key, body)

        svc.report.publish = capture

    def of(self, kind: str) -> list[dict[str, Any]]:
        return [e for e in self.all if e["type"] == kind]


async def up(svc: Service, task: asyncio.Task[Any], timeout: float = 60.0) -> None:
    """Until the service runs (setpoint thread started) and has heard the autopilot."""
    deadline = time.monotonic() + timeout
    while not (svc.flight.seen_link and svc._sender_failure is not None and svc.sender.native_id is not None):
        assert time.monotonic() < deadline and not task.done(), "service did not come up"
        await asyncio.sleep(0.05)


async def until(pred: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.05)


@contextlib.asynccontextmanager
async def serving(svc: Service, before_stop: Callable[[], None] | None = None,
                  timeout: float = 60.0) -> AsyncIterator[asyncio.Task[Any]]:
    """The service running and up (`up`) for the body, then stopped as the unit stops it (the
    SIGTERM request: hand over, leave) whatever the body did; `before_stop` first (heal the
    link faults a test injected, so that the hand-over can be heard)."""
    task = asyncio.create_task(svc.run())
    try:
        await up(svc, task, timeout)
        yield task
    finally:
        if before_stop is not None:
            before_stop()
        svc.requested.set()
        await asyncio.wait_for(task, 30)
