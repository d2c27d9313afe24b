"""`[live] foxglove = "HOST:PORT"`: the recording's channels, live, over the Foxglove WebSocket
protocol (Foxglove app or web: "Open connection", `ws://HOST:PORT`).

The server is the Foxglove SDK's (Rust, threads of its own, no GIL held while it serves), so a
slow viewer costs the service nothing but the SDK's bounded per-client queue: it drops for that
client, never waits. It gets exactly what the MCAP file gets, from the recorder's writer thread.
"""

from __future__ import annotations

import logging
from typing import Any

from companion import channels as ch
from companion.config import parse_address
from companion.wire.zenoh import loopback

log = logging.getLogger("companion")


class LiveSink:
    def __init__(self, server: Any, context: Any) -> None:
        self.server = server
        self.context = context
        self._channels: dict[str, Any] = {}

    @property
    def port(self) -> int:
        return int(self.server.port)

    @classmethod
    def start(cls, address: str, vehicle: str) -> LiveSink:
        import foxglove

        host, port = parse_address(address)
        if not loopback(host):
            log.warning("!!! [live] foxglove serves the flight on %s:%d, beyond this machine: anyone who reaches it "
                        "sees the vehicle's position, plans and every message, unauthenticated and unencrypted. "
                        "Keep it on 127.0.0.1 and use an SSH tunnel (docs/recording.md).", host, port)
        ctx = foxglove.Context()
        server = foxglove.start_server(name=f"bezier-companion {vehicle}", host=host, port=port, context=ctx)
        log.info("live view: Foxglove WebSocket server on ws://%s:%d", host, server.port)
        return cls(server, ctx)

    def write(self, topic: str, data: bytes, log_time: int) -> None:
        channel = self._channels.get(topic)
        if channel is None:
            import foxglove

            spec = ch.spec(topic)
            channel = foxglove.Channel(topic, schema=foxglove.Schema(name=spec.schema_name, encoding=spec.schema_encoding,
                                                                     data=spec.schema_data),
                                       message_encoding=spec.message_encoding, context=self.context)
            self._channels[topic] = channel
        channel.log(data, log_time=log_time)

    def close(self, stats: dict[str, Any]) -> None:
        self.server.stop()
