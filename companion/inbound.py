"""Inbound messages: one reader per kind, and what is refused on arrival.

Zenoh puts come in through `ZenohIO.inbox`; small obstacle messages are read at once, the rest
in order (large ones decoded off the loop), each read message handed to its one handler (the
navigator's for missions, obstacles and changes; the commands' for commands). Refused on
arrival, never acted on, each said as a `rejected` event: full queues, too many at once, a put
on another key expression than this vehicle's exact key, and MAVLink messages not from the
bound autopilot.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import math
import time
from typing import Any

from companion.commands import Commands
from companion.config import Config
from companion.fleet import FleetFrame
from companion.navigator import Navigator
from companion.report import Reporter
from companion.runtime import Runtime
from companion.tap import Tap
from companion.wire.errors import InternalError, MessageError, Oversized, quote
from companion.wire.mavlink import MavlinkLink
from companion.wire.messages import Change, Command, Message, MissionSpec, ObstacleUpdate, read
from companion.wire.zenoh import ZenohIO

log = logging.getLogger("companion")

INLINE_DECODE_BYTES = 4096


class Inbound:
    def __init__(self, cfg: Config, stop: asyncio.Event, report: Reporter, link: MavlinkLink, fleet: FleetFrame,
                 runtime: Runtime, tap: Tap, navigator: Navigator, commands: Commands) -> None:
        self.cfg = cfg
        self.stop = stop  # the service's loops end
        self.report = report
        self.link = link
        self.fleet = fleet
        self.runtime = runtime
        self.tap = tap
        self.navigator = navigator
        self.commands = commands
        self.zio: ZenohIO | None = None  # set once Zenoh is open (attach)
        self.tasks: list[asyncio.Task[Any]] = []  # the handlers running
        self._ordered: asyncio.Queue[tuple[str, bytes | Oversized, float]] = asyncio.Queue()
        self._missions: list[asyncio.Task[Any]] = []  # mission handlers not yet done
        self._drops = 0
        self._drop_said = -math.inf
        self._wrong_said: dict[str, float] = {}  # key expression -> when its refusal was said

    def attach(self, zio: ZenohIO) -> None:
        """Zenoh's inbound side: what it refuses on arrival is said here."""
        self.zio = zio
        zio.on_refused = self.refused
        zio.on_wrong_key = self.wrong_key

    async def inbox_loop(self) -> None:
        """Small obstacle messages (pop-ups) are handled at once; the rest keep their order in
        `ordered_loop`, where one large mission may take a while to validate: a pop-up must not
        wait behind it. (Obstacle updates do not depend on a mission being loaded first: a
        mission is planned against the obstacles known when it is planned.) Nothing a message
        does ends this loop: the last-resort guard turns it into a rejection and an error."""
        assert self.zio is not None
        self.zio.on_dropped = self._dropped
        while not self.stop.is_set():
            kind, payload, arrived = await self.zio.inbox.get()
            try:
                self.tap.inbound(kind, payload, arrived)
                if kind == "obstacles" and len(payload) <= INLINE_DECODE_BYTES:
                    context: dict[str, Any] = {"home": self.link.state.home, "home_pending": False,
                                               "fleet": self.fleet.for_messages(),
                                               "autopilot": self.link.state.autopilot}
                    msg = read(kind, payload, self.cfg, context["home"], fleet=context["fleet"],
                               autopilot=context["autopilot"])
                    self.tap.decoded(kind, payload, context, msg, arrived)
                    self.dispatch(kind, payload, arrived, msg)
                elif self._ordered.qsize() >= self.cfg.limits.max_queued_messages:
                    self._dropped(kind, len(payload))
                else:
                    self._ordered.put_nowait((kind, payload, arrived))
            except Exception as exc:
                self._unforeseen(kind, payload, exc)
            # one message per loop step: a backlog of small messages decoded here must not
            # hold up the timers (periodic status, stall checks) behind it
            await asyncio.sleep(0)

    async def ordered_loop(self) -> None:
        while not self.stop.is_set():
            kind, payload, arrived = await self._ordered.get()
            # JSON Schema validation is pure Python (~0.1 ms per waypoint): large messages off
            # the loop, small ones (a command: well under a millisecond) right here, which
            # spares two thread hand-offs. One message at a time, so the order is kept.
            try:
                context: dict[str, Any] = {"home": self.link.state.home,
                                           "home_pending": self.link.state.home_pending,
                                           "fleet": self.fleet.for_messages(),
                                           "autopilot": self.link.state.autopilot}
                job = functools.partial(read, kind, payload, self.cfg, context["home"],
                                        home_pending=context["home_pending"], fleet=context["fleet"],
                                        autopilot=context["autopilot"])
                msg = job() if len(payload) <= INLINE_DECODE_BYTES else \
                    await asyncio.get_running_loop().run_in_executor(self.runtime.decode_pool, job)
                self.tap.decoded(kind, payload, context, msg, arrived)
                self.dispatch(kind, payload, arrived, msg)
            except Exception as exc:
                self._unforeseen(kind, payload, exc)

    def _unforeseen(self, kind: str, payload: bytes | Oversized, exc: BaseException) -> None:
        """The last resort at the loop boundary: a rejection and an error event, never an exit."""
        log.error("message on %s: unforeseen %r", kind, exc, exc_info=exc)
        what = f"{type(exc).__name__}: {quote(str(exc))}"
        with contextlib.suppress(Exception):
            self.report.reject(kind, "", f"internal error while handling the message: {what}", bytes=len(payload))
            self.report.event("error", f"{kind}: internal error while handling a message: {what}; "
                              "holding the current plan", key=kind)

    def _dropped(self, kind: str, size: int) -> None:
        """A message refused because the inbound queues are full: said at most once a second."""
        self._drops += 1
        now = time.monotonic()
        if now - self._drop_said >= 1.0:
            n, self._drops, self._drop_said = self._drops, 0, now
            lim = self.cfg.limits.max_queued_messages
            self.report.reject(kind, "", f"{n} message(s) dropped: {lim} messages are already queued "
                               f"([limits] max_queued_messages = {lim})", bytes=size, dropped=n)

    def refused(self, counts: dict[str, int]) -> None:
        """Messages refused on arrival over `[limits] inbound_rate`: one event for all of them."""
        lim = self.cfg.limits
        total = sum(counts.values())
        each = ", ".join(f"{n} on {k}" for k, n in sorted(counts.items()))
        self.report.reject(next(iter(sorted(counts))) if len(counts) == 1 else "", "",
                           f"{total} message(s) refused on arrival ({each}): more than {lim.inbound_burst:g} at once "
                           f"or {lim.inbound_rate:g} a second per key ([limits] inbound_rate, inbound_burst)",
                           refused=counts)

    def mavlink_ignored(self, counts: dict[str, int], rebound: str | None) -> None:
        """MAVLink messages not from the bound autopilot (never acted on), or a re-bind."""
        gate = self.link.gate
        if rebound is not None:
            self.report.event("mavlink_peer", f"the autopilot's address changed ({rebound}) after its old address "
                              f"was silent for over {self.cfg.mavlink.link_timeout:g} s ([mavlink] link_timeout): "
                              "re-bound to it", rebound=rebound)
            return
        words = {"other_address": "from another address than the autopilot's",
                 "other_id": "from another system or component id",
                 "unsigned": "unsigned or not signed with our key ([mavlink] require_signed_inbound)",
                 "before_binding": "before the autopilot's first heartbeat"}
        where = f" (bound to {gate.address[0]}:{gate.address[1]})" if gate is not None and gate.address else ""
        text = "; ".join(f"{n} {words.get(why, why)}" for why, n in counts.items())
        self.report.event("mavlink_ignored", f"MAVLink messages ignored, not from the autopilot "
                          f"{self.cfg.vehicle.sysid}/{self.cfg.vehicle.autopilot_component}{where}: {text}",
                          ignored=counts, total=dict(gate.ignored) if gate is not None else None)

    def wrong_key(self, kind: str, key: str, size: int) -> None:
        """A put on a key expression other than this vehicle's exact key: never acted on. One
        event per key expression a second (a put on `bezier/drone1/*` reaches all four kinds)."""
        now = time.monotonic()
        if now - self._wrong_said.get(key, -math.inf) < 1.0:
            return
        if len(self._wrong_said) > 64:  # bounded: a peer may try many expressions
            self._wrong_said = {k: t for k, t in self._wrong_said.items() if now - t < 1.0}
        self._wrong_said[key] = now
        self.report.reject(kind, "key_expr", f"a put on key expression {quote(key, 80)} is refused: only this "
                           f"vehicle's exact keys ({self.cfg.key('<kind>')}) are acted on, never a wildcard or a "
                           "key matching several vehicles or kinds (send one put per vehicle)",
                           key_expr=key[:100], bytes=size)

    def dispatch(self, kind: str, payload: bytes | Oversized, arrived: float, msg: Message | MessageError) -> None:
        if isinstance(msg, MessageError):
            self.report.reject(kind, msg.field, msg.reason, bytes=len(payload))
            if isinstance(msg, InternalError):
                self.report.event("error", f"{kind}: {msg.reason}; holding the current plan", key=kind)
            return
        handler: Any
        if isinstance(msg, MissionSpec):
            self._missions = [t for t in self._missions if not t.done()]
            lim = self.cfg.limits.max_pending_missions
            if len(self._missions) >= lim:
                self.report.reject(kind, "", f"mission {msg.id}: {len(self._missions)} missions are already being "
                                   f"checked or planned ([limits] max_pending_missions = {lim})", mission=msg.id)
                return
            handler = self.navigator.on_mission
        elif isinstance(msg, ObstacleUpdate):
            handler = self.navigator.on_obstacles
        elif isinstance(msg, Change):
            handler = self.navigator.on_change
        elif isinstance(msg, Command):
            handler = self.commands.on_command
        else:  # pragma: no cover - read() makes only these
            raise TypeError(f"no handler for {type(msg).__name__}")
        task = asyncio.create_task(self._guard(kind, handler(msg, arrived)))
        if isinstance(msg, MissionSpec):
            self._missions.append(task)
        self.tasks.append(task)
        self.tasks = [t for t in self.tasks if not t.done()]

    async def _guard(self, kind: str, coro: Any) -> None:
        try:
            await coro
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # a bug in one handler must not stop the service
            log.exception("handler for %s failed", kind)
            self.report.event("error", f"{kind}: internal error: {exc!r}; holding the current plan", key=kind)
