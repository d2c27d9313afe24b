"""Issue 22.5: the service's life in phases (set up, start, run, stop), each resource undone in
reverse as it was taken, whichever phase failed: a warm-up that fails leaves no Zenoh session,
no MAVLink socket, no worker pool and no logging queue behind, and the Zenoh endpoint can be
listened on again at once; a normal run ends the same way."""

from __future__ import annotations

import asyncio
import logging
import logging.handlers
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh
from companionkit import service_for, serving

from companion.service import Service
from sitl_mock import MockAutopilot, MockConfig

POOL_THREADS = ("planner", "urgent", "replan", "encode", "decode", "brake")


def _pool_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.is_alive() and t.name.startswith(POOL_THREADS)]


def _nothing_left(svc: Service, before: list[str]) -> None:
    assert svc.zio is not None and svc.zio.session is None, "the Zenoh session is still open"
    assert svc.link.conn is None, "the MAVLink connection is still open"
    assert not any(isinstance(h, logging.handlers.QueueHandler) for h in logging.getLogger().handlers)
    deadline = time.monotonic() + 5.0
    while (left := sorted(set(_pool_threads()) - set(before))) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not left, f"worker threads left running: {left}"
    # the endpoint the service listened on is free: another session takes it at once
    conf = zenoh.Config()
    conf.insert_json5("listen/endpoints", f'["{svc.cfg.zenoh.listen[0]}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("mode", '"peer"')
    zenoh.open(conf).close()


@pytest.fixture
def mock(tmp_path: Path) -> Any:
    m = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"],
                                 log_path=str(tmp_path / "f.jsonl"))).start()
    yield m
    m.stop()


def test_a_failed_warm_up_leaves_nothing_open(mock: MockAutopilot) -> None:
    before = _pool_threads()
    svc = service_for(mock)

    async def fails() -> None:
        await asyncio.sleep(0.1)  # Zenoh, the recorder and MAVLink are open by now
        raise RuntimeError("warm-up failed (injected)")

    svc._warm_up = fails  # type: ignore[method-assign]
    with pytest.raises(RuntimeError, match="injected"):
        asyncio.run(svc.run())
    _nothing_left(svc, before)


def test_a_run_stopped_as_the_unit_stops_it_leaves_nothing_open(mock: MockAutopilot) -> None:
    before = _pool_threads()
    svc = service_for(mock)
    said: list[dict[str, Any]] = []
    publish = svc.report.publish

    def capture(key: str, body: dict[str, Any]) -> None:
        if key == "events":
            said.append(body)
        if publish is not None:
            publish(key, body)

    svc.report.publish = capture

    async def go() -> None:
        async with serving(svc):
            await asyncio.sleep(0.5)

    asyncio.run(go())
    assert [e["type"] for e in said if e["type"] in ("started", "stopped")] == ["started", "stopped"]
    _nothing_left(svc, before)
