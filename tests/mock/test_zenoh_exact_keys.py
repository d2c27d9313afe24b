"""Issue 21.2 with real Zenoh on loopback: puts on a wildcard key expression are refused (one
`rejected` event naming the key) and never acted on; clients take status and events only from
the companion they addressed (the session that answers the status query), and say when they
cannot tell."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

import zenoh
from companionkit import Events, service_for, serving, until, zenoh_client

from companion.cli_client import Origin
from sitl_mock import MockAutopilot, MockConfig


def _port(svc: Any) -> int:
    return int(svc.cfg.zenoh.listen[0].rsplit(":", 1)[1])


def test_wildcard_puts_are_refused_and_never_acted_on(tmp_path: Path) -> None:
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"],
                                    log_path=str(tmp_path / "f.jsonl"))).start()

    async def go() -> None:
        svc = service_for(mock)
        events = Events(svc)
        acted: list[Any] = []
        on_command = svc.commands.on_command

        async def recording(cmd: Any, arrived: float) -> None:
            acted.append(cmd)
            await on_command(cmd, arrived)

        svc.commands.on_command = recording  # type: ignore[method-assign]
        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 15, "position")
            client = zenoh_client(_port(svc))
            try:
                await asyncio.sleep(0.5)
                arm = b'{"command": "arm"}'
                client.put("bezier/*/command", arm)  # every vehicle at once
                client.put("bezier/inproc/*", arm)  # every kind of this vehicle
                client.put("bezier/**", arm)
                await until(lambda: len(events.of("rejected")) >= 3, 10, "three refusals")
                await asyncio.sleep(1.0)
                keys = [e["key_expr"] for e in events.of("rejected")]
                # one event per key expression, though `bezier/inproc/*` reached four subscribers
                assert sorted(keys) == sorted(["bezier/*/command", "bezier/**", "bezier/inproc/*"]), keys
                assert all(e["field"] == "key_expr" and "one put per vehicle" in e["reason"]
                           for e in events.of("rejected"))
                assert not acted and not svc.link.state.armed
                # the exact key is obeyed (the same session, the same payload)
                client.put("bezier/inproc/command", arm)
                await until(lambda: acted, 10, "the exact put acted on")
            finally:
                client.close()

    try:
        asyncio.run(go())
    finally:
        mock.stop()


def test_clients_take_status_and_events_only_from_the_companion_they_addressed(tmp_path: Path) -> None:
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"],
                                    log_path=str(tmp_path / "f.jsonl"))).start()

    async def go() -> None:
        svc = service_for(mock)
        async with serving(svc):
            port = _port(svc)
            operator, faker = zenoh_client(port), zenoh_client(port)
            try:
                await asyncio.sleep(0.5)
                origin = await asyncio.to_thread(Origin, operator, "bezier/inproc")
                assert origin.companion == svc.zio.zid, origin.note  # type: ignore[union-attr]
                got: list[dict[str, Any]] = []

                def take(sample: Any) -> None:
                    body = json.loads(sample.payload.to_bytes())
                    if origin.accepts("events", sample, body):
                        got.append(body)

                sub = operator.declare_subscriber("bezier/inproc/events", take)
                await asyncio.sleep(0.5)
                fake = {"type": "completed", "key": "command", "message": "fake"}
                faker.put("bezier/inproc/events", json.dumps(fake).encode())  # no session id
                faker.put("bezier/inproc/events", json.dumps({**fake, "session": str(faker.zid())}).encode())
                faker.put("bezier/*/events", json.dumps({**fake, "session": svc.zio.zid}).encode())  # type: ignore[union-attr]
                svc.report.event("note", "from the companion")
                await until(lambda: got, 5, "the companion's event")
                await asyncio.sleep(0.5)
                assert [e["message"] for e in got] == ["from the companion"], got
                assert origin.summary() is not None and "not from the addressed companion" in origin.summary()  # type: ignore[operator]
                sub.undeclare()
                # a second session answering as the vehicle: the client cannot tell, and says so
                q = faker.declare_queryable("bezier/inproc/status",
                                            lambda query: query.reply("bezier/inproc/status", b'{"state": "READY"}'))
                await asyncio.sleep(0.5)
                two = await asyncio.to_thread(Origin, operator, "bezier/inproc")
                assert two.companion is None and "cannot tell which is the companion" in two.note, two.note
                q.undeclare()
            finally:
                operator.close()
                faker.close()
        # nobody answering: said, not guessed
        alone = zenoh.Config()
        alone.insert_json5("scouting/multicast/enabled", "false")
        alone.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
        lonely = zenoh.open(alone)
        try:
            t0 = time.monotonic()
            none = await asyncio.to_thread(Origin, lonely, "bezier/inproc", 0.5)
            assert none.companion is None and "no companion answered" in none.note and time.monotonic() - t0 < 5
        finally:
            lonely.close()

    try:
        asyncio.run(go())
    finally:
        mock.stop()
