"""The setpoint-stream watchdog: setpoints that stop leaving while streaming are noticed."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace
from typing import Any

from companion.config import Config
from companion.stalls import StallWatch


class _Report:
    def __init__(self) -> None:
        self.events: list[tuple[str, str, dict[str, Any]]] = []

    def event(self, kind: str, message: str, **extra: Any) -> None:
        self.events.append((kind, message, extra))


def test_watchdog_reports_a_stall_and_the_resumption() -> None:
    report = _Report()
    fake = SimpleNamespace(cfg=Config(), stop=asyncio.Event(), report=report, setpoints_stalled=False,
                           link=SimpleNamespace(sent_setpoints=0), control=SimpleNamespace(streaming=True))

    async def main() -> None:
        task = asyncio.create_task(StallWatch.setpoint_watchdog(fake))  # type: ignore[arg-type]
        for _ in range(10):  # flowing: 50 Hz
            fake.link.sent_setpoints += 1
            await asyncio.sleep(0.02)
        assert not fake.setpoints_stalled
        await asyncio.sleep(0.3)  # stalled
        assert fake.setpoints_stalled
        fake.link.sent_setpoints += 1
        await asyncio.sleep(0.06)
        assert not fake.setpoints_stalled
        fake.control.streaming = False  # not streaming: silence is expected
        await asyncio.sleep(0.3)
        assert not fake.setpoints_stalled
        fake.stop.set()
        await task

    asyncio.run(main())
    kinds = [k for k, m, _ in report.events if "event loop" not in m]
    assert kinds == ["error", "setpoints_resumed"], report.events
    assert "setpoints stopped leaving" in report.events[0][1]
    assert report.events[0][2]["silence_ms"] >= 100
