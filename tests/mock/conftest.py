"""Fixture: an in-process mock on a free UDP port and a pymavlink client talking to it."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from mockkit import Client, free_udp_port

from sitl_mock import MockAutopilot, MockConfig


@pytest.fixture
def make_mock(tmp_path: Path) -> Iterator[Callable[..., tuple[MockAutopilot, Client]]]:
    started: list[tuple[MockAutopilot, Client]] = []

    def factory(autopilot: str = "px4", **kw: Any) -> tuple[MockAutopilot, Client]:
        port = free_udp_port()
        kw.setdefault("log_path", str(tmp_path / f"{autopilot}-{port}.jsonl"))
        kw.setdefault("log_rate_hz", 50.0)
        if autopilot == "ardupilot":
            # FAST: the EKF origin at once, for tests not about it (stock: 40 s; test_mock_ardupilot_strict).
            kw.setdefault("ekf_origin_delay_s", 0.0)
        cfg = MockConfig(autopilot=autopilot, endpoints=[f"udpin:127.0.0.1:{port}"], **kw)
        mock = MockAutopilot(cfg).start()
        client = Client(port)
        client.hello()
        started.append((mock, client))
        return mock, client

    yield factory
    for mock, client in started:
        client.close()
        mock.stop()
