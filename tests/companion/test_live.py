"""The live view: a client speaking the Foxglove WebSocket protocol (with the `websockets`
package) gets serverInfo, the channel advertisements with their schemas, subscribes, and
receives what the recorder records.

The client offers both names of the protocol, as the Foxglove app and Lichtblick (since its PR 819,
December 2025) do:
`foxglove.websocket.v1` and `foxglove.sdk.v1`, the same protocol renamed by Foxglove in 2025.
The Foxglove SDK's server (0.30) accepts only the new name (docs/recording.md)."""

from __future__ import annotations

import asyncio
import json
import logging
import struct
import threading
import time
from typing import Any

import pytest
import websockets
from recorder_support import Wire, config

from companion.config import parse_address
from companion.live import loopback
from companion.recorder import Recorder


def test_addresses_parse_and_default_to_loopback() -> None:
    assert parse_address("127.0.0.1:8765") == ("127.0.0.1", 8765)
    assert parse_address(":9000") == ("127.0.0.1", 9000)
    assert parse_address("[::1]:8765") == ("::1", 8765)
    for bad in ("8765", "host:", "host:99999", "host:port", "host:-1"):
        with pytest.raises(ValueError, match="HOST:PORT"):
            parse_address(bad)
    assert loopback("127.0.0.1") and loopback("::1") and loopback("localhost")
    assert not loopback("0.0.0.0") and not loopback("192.168.1.2") and not loopback("drone.local")


def test_serving_beyond_loopback_is_said_loudly(caplog: pytest.LogCaptureFixture) -> None:
    from companion.live import LiveSink

    with caplog.at_level(logging.WARNING, logger="companion"):
        sink = LiveSink.start("0.0.0.0:0", "v")
    sink.close({})
    assert any("!!!" in r.message and "beyond this machine" in r.message for r in caplog.records)


async def _client(port: int, want: str, feed: threading.Event) -> tuple[dict[str, Any], dict[str, Any], list[bytes]]:
    offered = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=offered) as ws:  # type: ignore[arg-type]
        assert ws.subprotocol in offered
        info = json.loads(await asyncio.wait_for(ws.recv(), 10))
        feed.set()  # channels appear as the recorder first writes on them
        channel = None
        while channel is None:
            msg = await asyncio.wait_for(ws.recv(), 10)
            if isinstance(msg, str):
                body = json.loads(msg)
                if body.get("op") == "advertise":
                    channel = next((c for c in body["channels"] if c["topic"] == want), None)
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": channel["id"]}]}))
        got: list[bytes] = []
        while len(got) < 3:
            msg = await asyncio.wait_for(ws.recv(), 10)
            if isinstance(msg, bytes) and msg[0] == 0x01:  # messageData
                sub, _t = struct.unpack_from("<IQ", msg, 1)
                assert sub == 7
                got.append(msg[13:])
        return info, channel, got


@pytest.mark.parametrize("topic", ["/out/status", "/mavlink/out/SET_POSITION_TARGET_LOCAL_NED"])
def test_a_foxglove_client_subscribes_and_receives_the_recorded_channels(topic: str) -> None:
    rec = Recorder(config(live="127.0.0.1:0"))
    rec.open()
    try:
        port = rec.sinks[0].port  # type: ignore[attr-defined]
        feed, stop = threading.Event(), threading.Event()
        wire = Wire(rec.mavlink_sent)

        def publish() -> None:
            feed.wait(10)
            k = 0
            while not stop.is_set():
                k += 1
                rec.outbound("status", json.dumps({"state": "READY", "n": k}).encode(), time.monotonic())
                wire.setpoint(k)
                time.sleep(0.02)

        th = threading.Thread(target=publish, daemon=True)
        th.start()
        try:
            info, channel, got = asyncio.run(_client(port, topic, feed))
        finally:
            stop.set()
            th.join()
    finally:
        rec.close()
    assert info["op"] == "serverInfo" and "bezier-companion" in info["name"]
    assert channel["encoding"] == "json" and channel["schemaEncoding"] == "jsonschema"
    assert json.loads(channel["schema"])["type"] == "object"
    bodies = [json.loads(b) for b in got]
    if topic == "/out/status":
        assert all(b["state"] == "READY" for b in bodies)
        assert [b["n"] for b in bodies] == sorted(b["n"] for b in bodies)
    else:
        assert all(b["mavpackettype"] == "SET_POSITION_TARGET_LOCAL_NED" for b in bodies)


def test_a_bad_address_is_a_configuration_error() -> None:
    from companion.config import ConfigError, config_from_dict

    with pytest.raises(ConfigError, match=r"live.foxglove: expected HOST:PORT"):
        config_from_dict({"live": {"foxglove": "localhost"}})
    assert config_from_dict({"live": {"foxglove": "127.0.0.1:8765"}}).live.foxglove == "127.0.0.1:8765"
