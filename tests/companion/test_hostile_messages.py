"""Issue 14: what a hostile peer sent, each case answered with a reason (and never a crash)."""

from __future__ import annotations

import asyncio
import json
import time
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from companion.config import Config, LimitsConfig, config_from_dict
from companion.inbound import Inbound
from companion.obstacles import ObstacleStore
from companion.tap import NO_TAP
from companion.wire import decode, messages
from companion.wire.errors import MAX_REASON
from companion.wire.messages import (
    Command,
    InternalError,
    MessageError,
    ObstacleUpdate,
    Oversized,
    read,
)
from planner_core.geometry import polytope_from_vertices

CFG = Config()
CUBE = [[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)]
BOX_A = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]


def rejected(kind: str, payload: bytes | dict[str, Any] | Oversized, cfg: Config = CFG) -> MessageError:
    raw = payload if isinstance(payload, bytes | Oversized) else json.dumps(payload).encode()
    out = read(kind, raw, cfg)
    assert isinstance(out, MessageError), out
    assert not isinstance(out, InternalError), out
    assert out.reason and len(out.reason) <= MAX_REASON and len(out.field) <= 100
    return out


@pytest.mark.parametrize(
    ("kind", "payload", "field", "words"),
    [
        # one 5 kB message stopped the service
        ("command", b'{"command": "takeoff", "altitude": ' + b"9" * 5000 + b"}", "", "max_number_chars"),
        ("command", b'{"command": "takeoff", "altitude": ' + b"9" * 400 + b"}", "", "max_number_chars"),
        ("command", b'{"command": "takeoff", "altitude": 1' + b"0" * 30 + b"}", "altitude", "max_number"),
        ("obstacles", b'{"add":[{"id":"a","A":-1,"b":[1]}]}', "add[0].A", "not of type 'array'"),
        ("obstacles", b'{"add":[{"id":"a","A":1.5,"b":[1]}]}', "add[0].A", "not of type 'array'"),
        ("obstacles", b'{"add":[{"id":"a","A":[[1,0,0]],"b":-1}]}', "add[0].b", "not of type 'array'"),
        ("obstacles", b'{"add":[{"id":"a","vertices":-1}]}', "add[0].vertices", "not of type 'array'"),
        ("mission", b'{"id":"m","waypoints":-1e300}', "waypoints", "max_number"),
        ("mission", b'{"id":"m","waypoints":"x"}', "waypoints", "not of type 'array'"),
        ("mission", b"[" * 100_000, "", "max_depth"),
        ("mission", b'{"a":' * 40 + b"1" + b"}" * 40, "a" + ".a" * 12, "max_depth"),
        ("change", b"{" * 5000, "", ""),
        # fields a command does not take
        ("command", {"command": "arm", "altitude": 3}, "altitude", "only takeoff"),
        ("command", {"command": "start", "speed": 3}, "speed", "takes no"),
        # degenerate obstacles
        ("obstacles", {"add": [{"id": "a", "A": [[1, 0, 0]], "b": [1]}]}, "add[0]", "unbounded"),
        ("obstacles", {"add": [{"id": "a", "A": BOX_A, "b": [-1, 0, 1, 1, 1, 1]}]}, "add[0]", "empty"),
        ("obstacles", {"add": [{"id": "a", "A": BOX_A, "b": [0, 0, 1, 1, 1, 1]}]}, "add[0]", "flat"),
        ("obstacles", {"add": [{"id": "a", "A": BOX_A, "b": [900, 900, 1, 1, 1, 1]}]}, "add[0]", "max_obstacle_extent"),
        ("obstacles", {"add": [{"id": "a", "A": BOX_A, "b": [1e300, 1, 1, 1, 1, 1]}]}, "add[0].b[0]", "max_number"),
        ("obstacles", {"add": [{"id": "a", "vertices": [[1e300, 0, 0], *CUBE]}]}, "add[0].vertices[0][0]", "max_number"),
        ("obstacles", {"add": [{"id": "a", "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]}]},
         "add[0].vertices", "coplanar"),
        ("obstacles", {"add": [{"id": "a", "vertices": []}]}, "add[0].vertices", "too short"),
        ("obstacles", {"add": [{"id": "a", "A": [[0, 0, 0]] * 6, "b": [1] * 6}]}, "add[0]", "zero"),
        ("mission", {"id": "m", "waypoints": [[0, 0, -1]], "obstacles": [{"A": [[1, 0, 0]], "b": [1]}]},
         "obstacles[0]", "unbounded"),
        # array lengths
        ("obstacles", {"add": [{"id": "a", "A": [[1, 0, 0]] * 33, "b": [1] * 33}]}, "add[0].A", "max_obstacle_planes"),
        ("mission", {"id": "m", "waypoints": [[0, 0, -1]] * 5001}, "waypoints", "max_waypoints"),
    ],
)
def test_hostile_payloads_are_rejected_with_a_reason(kind: str, payload: Any, field: str, words: str) -> None:
    err = rejected(kind, payload)
    assert err.field == field, err
    assert words in err.reason, err


def test_issue_reproducer_prints_a_message_error() -> None:
    out = read("obstacles", b'{"add":[{"id":"a","A":-1,"b":[1]}]}', Config())
    assert isinstance(out, MessageError)


def test_reasons_quote_at_most_about_100_characters() -> None:
    err = rejected("obstacles", {"add": [{"id": "x" * 100_000, "A": BOX_A, "b": [1] * 6}]})
    assert err.field == "add[0].id" and "max_string_chars" in err.reason and len(err.reason) < 250
    err = rejected("mission", {"id": "m", "waypoints": [[0, 0, 0]], "x" * 200: 1})
    assert len(err.reason) < 250
    err = rejected("command", {"command": "y" * 250})
    assert len(err.reason) <= 200, err


def test_oversized_payload_is_refused_from_its_size() -> None:
    err = rejected("mission", Oversized(100 << 20))
    assert "104857600 bytes exceeds the limit of 1048576" in err.reason


def test_commands_take_only_their_fields() -> None:
    assert read("command", b'{"command": "takeoff", "altitude": 3}', CFG) == Command("takeoff", 3.0)
    assert read("command", b'{"command": "arm"}', CFG) == Command("arm", None)
    assert decode.schema("command")["else"] == {"properties": {"altitude": False, "origin": False}}


def test_limits_are_configurable_and_named() -> None:
    cfg = config_from_dict({"limits": {"max_obstacle_vertices": 8}})
    err = rejected("obstacles", {"add": [{"id": "a", "vertices": [*CUBE, [0.5, 0.5, 0.5]]}]}, cfg)
    assert "max_obstacle_vertices" in err.reason
    assert isinstance(read("obstacles", json.dumps({"add": [{"id": "a", "vertices": CUBE}]}).encode(), cfg),
                      ObstacleUpdate)


def test_the_last_resort_turns_a_bug_into_an_internal_error(monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(*_: Any) -> None:
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(messages, "obstacles_from_message", broken)
    out = read("obstacles", b'{"clear": true}', CFG)
    assert isinstance(out, InternalError) and "ZeroDivisionError" in out.reason


def test_hull_is_n_log_n() -> None:
    pts = np.random.default_rng(3).normal(size=(10_000, 3))
    t0 = time.perf_counter()
    poly = polytope_from_vertices(pts)
    assert time.perf_counter() - t0 < 1.0
    assert np.all(pts @ poly.A.T <= poly.b + 1e-9)
    cube = polytope_from_vertices(CUBE)
    assert cube.A.shape == (6, 3)


def test_obstacle_store_holds_at_most_its_limit() -> None:
    store = ObstacleStore(max_held=2)
    p = polytope_from_vertices(CUBE)
    assert store.refusal([("a", p), ("b", p)], [], False) is None
    store.update([("a", p), ("b", p)], [], False)
    why = store.refusal([("c", p)], [], False)
    assert why is not None and "max_obstacles_held" in why
    assert store.refusal([("a", p)], [], False) is None  # replacing one
    assert store.refusal([("c", p)], ["a"], False) is None
    assert store.refusal([("c", p), ("d", p)], [], True) is None


class _Report:
    def __init__(self) -> None:
        self.events: list[tuple[str, str]] = []

    def reject(self, key: str, field: str, reason: str, **_: Any) -> None:
        self.events.append(("rejected", f"{key}: {reason}"))

    def event(self, kind: str, message: str, **_: Any) -> None:
        self.events.append((kind, message))


def test_loop_boundary_guard_reports_and_goes_on() -> None:
    """An exception inside the inbound path is a rejection plus an error event, and the
    loop takes the next message."""
    report = _Report()
    seen: list[str] = []

    def dispatch(kind: str, payload: bytes, arrived: float, msg: Any) -> None:
        if payload == b"boom":
            raise RuntimeError("unforeseen")
        seen.append(kind)

    inbox: asyncio.Queue[tuple[str, bytes, float]] = asyncio.Queue()
    stop = asyncio.Event()
    fake = SimpleNamespace(
        zio=SimpleNamespace(inbox=inbox, on_dropped=None), stop=stop, cfg=CFG, report=report,
        link=SimpleNamespace(state=SimpleNamespace(home=None, autopilot=None)), _ordered=asyncio.Queue(), dispatch=dispatch, _dropped=lambda *a: None,
        tap=NO_TAP, fleet=SimpleNamespace(for_messages=lambda: None))
    fake._unforeseen = lambda kind, payload, exc: Inbound._unforeseen(fake, kind, payload, exc)  # type: ignore[arg-type]

    async def main() -> None:
        task = asyncio.create_task(Inbound.inbox_loop(fake))  # type: ignore[arg-type]
        inbox.put_nowait(("obstacles", b"boom", 0.0))
        inbox.put_nowait(("obstacles", b'{"clear": true}', 0.0))
        await asyncio.sleep(0.05)
        stop.set()
        task.cancel()

    asyncio.run(main())
    assert seen == ["obstacles"]
    kinds = [k for k, _ in report.events]
    assert kinds == ["rejected", "error"], report.events
    assert "RuntimeError" in report.events[1][1]


def test_defaults_are_documented_in_the_printed_config() -> None:
    from companion.config import config_to_toml

    text = config_to_toml()
    for name in ("max_obstacles_held", "max_pending_missions", "max_queued_messages", "max_number_chars",
                 "max_obstacle_planes", "max_depth"):
        assert name in text
        assert getattr(LimitsConfig(), name) > 0


def test_obstacle_checks_have_a_deadline() -> None:
    cfg = config_from_dict({"limits": {"decode_deadline": 1e-6}})
    obs = [{"id": f"o{i}", "vertices": [[x + 3 * i, y, z] for x, y, z in CUBE]} for i in range(20)]
    err = rejected("obstacles", {"add": obs}, cfg)
    assert err.field == "add" and "decode_deadline" in err.reason


def test_a_full_inbox_drops_and_says_so_once_a_second() -> None:
    from companion.wire.zenoh import ZenohIO

    cfg = config_from_dict({"limits": {"max_queued_messages": 3}})
    report = _Report()

    async def main() -> None:
        zio = ZenohIO(cfg, asyncio.get_running_loop())
        fake = SimpleNamespace(cfg=cfg, report=report, _drops=0, _drop_said=-1e9)
        zio.on_dropped = lambda kind, size: Inbound._dropped(fake, kind, size)  # type: ignore[arg-type]
        for _ in range(10):
            zio._enqueue("command", b"{}", 0.0)
        assert zio.inbox.qsize() == 3 and zio.dropped == 7

    asyncio.run(main())
    assert len(report.events) == 1 and "max_queued_messages = 3" in report.events[0][1]
