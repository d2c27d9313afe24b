"""Zenoh session: inbound keys to the event loop, outbound publishers, queryables.

Zenoh runs callbacks on its own threads. They only stamp the arrival time and
hand the raw payload to the loop with `call_soon_threadsafe`; decoding,
validation and every zenoh call happen on the loop thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from companion.admission import Admission
from companion.config import Config, ZenohConfig
from companion.tap import NO_TAP, Tap
from companion.wire.encode import encode
from companion.wire.errors import Oversized
from companion.wire.keys import ALIVE, INBOUND, OUTBOUND, QUERYABLE

log = logging.getLogger("companion")


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
    # A client (a companion joining a fleet's router) listens only where told: the default
    # loopback endpoint would be taken by a router on the same computer (and a client needs none).
    client_default = zc.mode == "client" and zc.listen == defaults.listen
    if listen and zc.listen and want("listen") and not client_default:
        cfg.insert_json5("listen/endpoints", json.dumps(list(zc.listen)))
    if zc.connect and want("connect"):
        cfg.insert_json5("connect/endpoints", json.dumps(list(zc.connect)))
    if want("multicast_scouting"):
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(zc.multicast_scouting))
    if want("shared_memory"):
        cfg.insert_json5("transport/shared_memory/enabled", json.dumps(zc.shared_memory))
    if not zc.config_file and listen:
        # Without a configuration file the service reaches out to nobody: peers it hears of
        # by scouting may connect to it (where it listens: loopback by default), it does not
        # connect to them (an outgoing session carries commands just as well).
        for how in ("multicast", "gossip"):
            cfg.insert_json5(f"scouting/{how}/autoconnect", json.dumps({"router": [], "peer": []}))
    return cfg


def _loopback(endpoint: str) -> bool:
    """True for an endpoint only this machine can reach (tcp/127.0.0.1:7447, udp/[::1]:0,
    unixsock-stream/...); False for anything else, including 0.0.0.0 and host names."""
    proto, _, rest = endpoint.partition("/")
    if proto.startswith("unixsock") or proto == "unixpipe":
        return True
    return loopback(rest.split("#")[0].rsplit(":", 1)[0].strip("[]"))


def loopback(host: str) -> bool:
    """A host name or address that only this computer reaches (localhost, 127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def exposure(cfg: zenoh.Config) -> list[str]:
    """Why commands may be accepted from an unauthenticated network peer ([] if they may not):
    the session listens or connects beyond loopback, or scouts, without user/password auth."""
    def get(key: str) -> Any:
        try:
            return json.loads(cfg.get_json(key))
        except Exception:  # a key this zenoh does not have
            return None

    auth = get("transport/auth/usrpwd") or {}
    if auth.get("dictionary_file"):
        return []
    why: list[str] = []
    mode = get("mode")
    listen = get("listen/endpoints") or []
    if isinstance(listen, dict):  # per-mode form {"router": [...], "peer": [...]}
        listen = (listen.get(mode) or []) if mode else [e for v in listen.values() for e in (v or [])]
    if not listen and mode != "client":  # a client listens nowhere unless told
        why.append("listening on zenoh's default endpoint (every interface)")
    why += [f"listening on {e}" for e in listen if not _loopback(str(e))]
    connect = get("connect/endpoints") or []
    if isinstance(connect, dict):
        connect = [e for v in connect.values() for e in (v or [])]
    # A client that presents a user and password to its router (a fleet: docs/fleet.md) is reached
    # only through that router, which authenticates every session and applies access control.
    client_of_secured_router = mode == "client" and bool(auth.get("user"))
    if not client_of_secured_router:
        why += [f"connecting to {e}" for e in connect if not _loopback(str(e))]
    auto = get("scouting/multicast/autoconnect")
    if get("scouting/multicast/enabled") and auto not in ({"router": [], "peer": []}, [], ""):
        why.append("connecting to any peer found by multicast scouting")
    return why


class ZenohIO:
    """Owns the session; `inbox` receives (kind, payload, arrival_monotonic)."""

    def __init__(self, cfg: Config, loop: asyncio.AbstractEventLoop) -> None:
        self.cfg = cfg
        self.loop = loop
        self.inbox: asyncio.Queue[tuple[str, bytes | Oversized, float]] = asyncio.Queue()
        # [limits] max_queued_messages: a message arriving to a full inbox is dropped and
        # counted; `on_dropped(kind, size)` (on the loop) says so.
        self.dropped = 0
        self.on_dropped: Callable[[str, int], None] | None = None
        # [limits] inbound_rate / inbound_burst per kind, decided in Zenoh's threads;
        # `on_refused({kind: count})` (on the loop, at most once a second) says what was refused.
        self.admission = Admission(cfg.limits.inbound_rate, cfg.limits.inbound_burst)
        self.on_refused: Callable[[dict[str, int]], None] | None = None
        self._refusal_due = False
        self._refusal_said = -math.inf
        self.tap: Tap = NO_TAP  # the flight recorder (companion/tap.py)
        # A put whose key expression is not this vehicle's exact key (`bezier/*/command`,
        # `bezier/drone1/*`, `bezier/**`: it reaches every subscriber it intersects) is never
        # acted on: `on_wrong_key(kind, key_expr, size)` (on the loop) says so.
        self.wrong_keys = 0
        self.on_wrong_key: Callable[[str, str, int], None] | None = None
        self.session: Any = None
        self.zid = ""  # this session's Zenoh id: status and events carry it (`session`)
        self.exposure: list[str] = []
        self._decls: list[Any] = []
        self._pubs: dict[str, Any] = {}
        self._query_handlers: dict[str, Callable[[], bytes | None]] = {}

    def open(self, query_handlers: dict[str, Callable[[], bytes | None]]) -> None:
        self._query_handlers = query_handlers
        zcfg = zenoh_config(self.cfg.zenoh)
        why = exposure(zcfg)
        if why:
            log.warning("!!! COMMANDS ARE ACCEPTED FROM UNAUTHENTICATED NETWORK PEERS: %s. Any peer that "
                        "reaches this endpoint can arm, take off and fly the vehicle. Use a secured "
                        "Zenoh configuration ([zenoh] config_file, see docs/security.md).", "; ".join(why))
        self.exposure = why
        self.session = zenoh.open(zcfg)
        self.zid = str(self.session.zid())
        for kind in INBOUND:
            self._decls.append(self.session.declare_subscriber(self.cfg.key(kind), self._inbound(kind)))
        for kind in OUTBOUND:
            self._pubs[kind] = self.session.declare_publisher(self.cfg.key(kind))
        for kind in QUERYABLE:
            self._decls.append(self.session.declare_queryable(self.cfg.key(kind), self._queried(kind)))
        self._decls.append(self.session.liveliness().declare_token(self.cfg.key(ALIVE)))

    def watch_fleet(self, on_trajectory: Callable[[str, bytes, float | None, float], None],
                    on_alive: Callable[[str, bool], None]) -> None:
        """The other vehicles' trajectories (`<prefix>/*/trajectory`) and liveliness (`<prefix>/*/alive`),
        each handed to the loop with the vehicle id from the key (docs/fleet.md)."""
        prefix = self.cfg.zenoh.prefix

        def vehicle(key: Any) -> str:
            parts = str(key).split("/")
            return parts[-2] if len(parts) >= 2 else ""

        def trajectory(sample: Any) -> None:
            arrived = time.time()  # here, not on the loop: its delays are not the network's
            if len(sample.payload) > self.cfg.limits.max_message_bytes:
                return
            self.loop.call_soon_threadsafe(on_trajectory, vehicle(sample.key_expr), sample.payload.to_bytes(),
                                           sent_time(sample.attachment), arrived)

        def alive(sample: Any) -> None:
            present = sample.kind != zenoh.SampleKind.DELETE
            self.loop.call_soon_threadsafe(on_alive, vehicle(sample.key_expr), present)

        self._decls.append(self.session.declare_subscriber(f"{prefix}/*/trajectory", trajectory))
        self._decls.append(self.session.liveliness().declare_subscriber(f"{prefix}/*/{ALIVE}", alive, history=True))

    def _inbound(self, kind: str) -> Callable[[Any], None]:
        limit = self.cfg.limits.max_message_bytes
        exact = self.cfg.key(kind)

        def callback(sample: Any) -> None:
            arrived = time.monotonic()
            if not self.admission.allow(kind, arrived):
                if not self._refusal_due:  # said by the loop, at most once a second
                    self._refusal_due = True
                    self.loop.call_soon_threadsafe(self._say_refusals)
                return
            size = len(sample.payload)  # without copying it out of zenoh
            key = str(sample.key_expr)
            if key != exact:
                self.loop.call_soon_threadsafe(self._wrong_key, kind, key, size)
                return
            payload: bytes | Oversized = Oversized(size) if size > limit else sample.payload.to_bytes()
            self.loop.call_soon_threadsafe(self._enqueue, kind, payload, arrived)

        return callback

    def _say_refusals(self) -> None:
        wait = self._refusal_said + 1.0 - time.monotonic()
        if wait > 0:
            self.loop.call_later(wait, self._say_refusals)
            return
        self._refusal_said = time.monotonic()
        self._refusal_due = False
        counts = self.admission.refusals()
        if counts and self.on_refused is not None:
            self.on_refused(counts)

    def _enqueue(self, kind: str, payload: bytes | Oversized, arrived: float) -> None:
        if self.inbox.qsize() >= self.cfg.limits.max_queued_messages:
            self.dropped += 1
            if self.on_dropped is not None:
                self.on_dropped(kind, len(payload))
            return
        self.inbox.put_nowait((kind, payload, arrived))

    def _wrong_key(self, kind: str, key: str, size: int) -> None:
        self.wrong_keys += 1
        if self.on_wrong_key is not None:
            self.on_wrong_key(kind, key, size)

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
            data = encode(obj)
            pub.put(data)
            self.tap.outbound(kind, data, time.monotonic())

    def publish_bytes(self, kind: str, payload: bytes) -> None:
        pub = self._pubs.get(kind)
        if pub is not None:
            if kind == "trajectory":  # its send time on our clock: the others measure theirs against it
                pub.put(payload, attachment=json.dumps({"sent": time.time()}).encode())
            else:
                pub.put(payload)
            self.tap.outbound(kind, payload, time.monotonic())

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


def sent_time(attachment: Any) -> float | None:
    """The send time a trajectory put carries (`{"sent": unix seconds}`), None if absent or bad."""
    if attachment is None:
        return None
    try:
        raw = attachment.to_bytes()
        if len(raw) > 200:
            return None
        sent = json.loads(raw).get("sent")
    except (ValueError, AttributeError, TypeError):
        return None
    return float(sent) if isinstance(sent, int | float) and not isinstance(sent, bool) and math.isfinite(sent) \
        else None
