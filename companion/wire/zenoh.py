"""Zenoh session: inbound keys to the event loop, outbound publishers, queryables.

Zenoh runs callbacks on its own threads. They only stamp the arrival time and
hand the raw payload to the loop with `call_soon_threadsafe`; decoding,
validation and every zenoh call happen on the loop thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from companion.config import Config, ZenohConfig
from companion.wire.encode import encode

INBOUND = ("mission", "obstacles", "change", "command")
OUTBOUND = ("status", "telemetry", "trajectory", "events")
QUERYABLE = ("plan", "status")


def zenoh_config(zc: ZenohConfig, *, listen: bool = True) -> zenoh.Config:
    """A zenoh.Config from our options (a JSON5 file, if given, is the base)."""
    defaults = ZenohConfig()
    if zc.config_file:
        cfg = zenoh.Config.from_file(str(Path(zc.config_file)))
        def want(name: str) -> bool:
            return bool(getattr(zc, name) != getattr(defaults, name))
    else:
        cfg = zenoh.Config()
        def want(name: str) -> bool:
            return True
    if want("mode"):
        cfg.insert_json5("mode", json.dumps(zc.mode))
    if listen and zc.listen and want("listen"):
        cfg.insert_json5("listen/endpoints", json.dumps(list(zc.listen)))
    if zc.connect and want("connect"):
        cfg.insert_json5("connect/endpoints", json.dumps(list(zc.connect)))
    if want("multicast_scouting"):
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(zc.multicast_scouting))
    return cfg


class ZenohIO:
    """Owns the session; `inbox` receives (kind, payload, arrival_monotonic)."""

    def __init__(self, cfg: Config, loop: asyncio.AbstractEventLoop) -> None:
        self.cfg = cfg
        self.loop = loop
        self.inbox: asyncio.Queue[tuple[str, bytes, float]] = asyncio.Queue()
        self.session: Any = None
        self._decls: list[Any] = []
        self._pubs: dict[str, Any] = {}
        self._query_handlers: dict[str, Callable[[], bytes | None]] = {}

    def open(self, query_handlers: dict[str, Callable[[], bytes | None]]) -> None:
        self._query_handlers = query_handlers
        self.session = zenoh.open(zenoh_config(self.cfg.zenoh))
        for kind in INBOUND:
            self._decls.append(self.session.declare_subscriber(self.cfg.key(kind), self._inbound(kind)))
        for kind in OUTBOUND:
            self._pubs[kind] = self.session.declare_publisher(self.cfg.key(kind))
        for kind in QUERYABLE:
            self._decls.append(self.session.declare_queryable(self.cfg.key(kind), self._queried(kind)))
        self._decls.append(self.session.liveliness().declare_token(self.cfg.key("alive")))

    def _inbound(self, kind: str) -> Callable[[Any], None]:
        def callback(sample: Any) -> None:
            arrived = time.monotonic()
            payload = sample.payload.to_bytes()
            self.loop.call_soon_threadsafe(self.inbox.put_nowait, (kind, payload, arrived))

        return callback

    def _queried(self, kind: str) -> Callable[[Any], None]:
        def callback(query: Any) -> None:
            self.loop.call_soon_threadsafe(self._answer, kind, query)

        return callback

    def _answer(self, kind: str, query: Any) -> None:
        try:
            body = self._query_handlers[kind]()
            if body is None:
                query.reply_err(encode({"error": f"no {kind} available"}))
            else:
                query.reply(self.cfg.key(kind), body)
        except Exception:  # a late or broken query must never take the loop down
            pass
        finally:
            query.drop()

    def publish(self, kind: str, obj: Any) -> None:
        pub = self._pubs.get(kind)
        if pub is not None:
            pub.put(encode(obj))

    def publish_bytes(self, kind: str, payload: bytes) -> None:
        pub = self._pubs.get(kind)
        if pub is not None:
            pub.put(payload)

    def close(self) -> None:
        for d in self._decls:
            with contextlib.suppress(Exception):
                d.undeclare()
        for p in self._pubs.values():
            with contextlib.suppress(Exception):
                p.undeclare()
        if self.session is not None:
            self.session.close()
            self.session = None
