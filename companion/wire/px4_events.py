"""PX4's events in words: the events metadata PX4 serves, fetched once per firmware, and decoding.

PX4 >= 1.14 reports arming refusals, failsafes and its checks as EVENT messages: an id and up to
40 argument bytes, whose text lives in the autopilot's own events metadata (all_events.json).
A ground station gets it as the MAVLink component-information service describes
(https://mavlink.io/en/services/component_information.html): COMPONENT_METADATA on
MAV_CMD_REQUEST_MESSAGE names the general metadata file (`mftp://...json.xz`), which names the
events file (type 4); both come over MAVLink FTP (https://mavlink.io/en/services/ftp.html:
OpenFileRO, ReadFile, TerminateSession), xz-compressed. The decoded metadata is cached on disk
per firmware (AUTOPILOT_VERSION flight_sw_version and uid, and the general file's CRC), so a
restart on the same firmware reads the cache instead of the link.

`EventsMetadata` is pure (the JSON in, text out); `Px4Events` fetches and caches over a
`MavlinkLink`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import lzma
import math
import os
import re
import struct
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from collections.abc import Iterable

    from companion.wire.mavlink import MavlinkLink
    from companion.wire.vehicle import Note

log = logging.getLogger("companion")

MSG_ID_COMPONENT_METADATA = 397
MSG_ID_AUTOPILOT_VERSION = 148
MAV_CMD_REQUEST_MESSAGE = 512
COMP_METADATA_TYPE_EVENTS = 4
_TYPES: dict[str, tuple[str, int]] = {
    "uint8_t": ("B", 1), "int8_t": ("b", 1), "uint16_t": ("H", 2), "int16_t": ("h", 2), "uint32_t": ("I", 4),
    "int32_t": ("i", 4), "uint64_t": ("Q", 8), "int64_t": ("q", 8), "float": ("f", 4),
}
# {1}, {2:.1}, {1:.1m}, {3m/s}: argument index (1-based), optional precision, optional unit
_PLACEHOLDER = re.compile(r"\{(\d+)(?::\.(\d+))?([^}]*)\}")
_PROFILE = re.compile(r"<profile\s+name=\"dev\">.*?</profile>", re.S)
_TAG = re.compile(r"</?[a-z]+[^>]*>")

# FTP (opcodes and NAK errors of the MAVLink FTP service)
OP_TERMINATE, OP_OPEN_RO, OP_READ = 1, 4, 5
OP_ACK, OP_NAK = 128, 129
ERR_EOF = 6
_FTP_HEADER = struct.Struct("<HBBBBBBI")
FTP_DATA_MAX = 239
FTP_TIMEOUT = 0.5  # s per request
FTP_RETRIES = 4
FTP_MAX_FILE = 8 * 1024 * 1024  # bytes: bounds what a confused autopilot can make us read


class MetadataError(Exception):
    """The events metadata could not be had (said, not fatal: events then stay numbers)."""


@dataclass(frozen=True)
class Described:
    name: str
    text: str
    group: str


class EventsMetadata:
    """The events of an all_events.json (PX4's build output, version 2), by wire id."""

    def __init__(self, data: dict[str, Any]) -> None:
        self.events: dict[int, tuple[str, dict[str, Any]]] = {}
        self.enums: dict[str, dict[str, Any]] = {}
        components = data.get("components")
        if not isinstance(components, dict):
            raise MetadataError("events metadata without 'components'")
        for cid, comp in components.items():
            namespace = str(comp.get("namespace", ""))
            for name, enum in (comp.get("enums") or {}).items():
                # PX4's all_events.json names an argument's enum "px4::arm_disarm_reason_t" (1.15),
                # or bare within its component ("navigation_mode_group_t")
                self.enums[f"{namespace}::{name}"] = enum
                self.enums[f"{namespace}::enums::{name}"] = enum
                self.enums.setdefault(name, enum)
            for group, body in (comp.get("event_groups") or {}).items():
                for sub_id, event in (body.get("events") or {}).items():
                    # keys are the 24-bit sub-ids; the wire id carries the component in the top byte
                    self.events[(int(cid) << 24) | (int(sub_id) & 0xFFFFFF)] = (str(group), event)

    def __len__(self) -> int:
        return len(self.events)

    def describe(self, event_id: int, arguments: bytes) -> Described | None:
        found = self.events.get(int(event_id))
        if found is None:
            return None
        group, event = found
        values = self._values(event.get("arguments") or [], arguments)
        text = _PLACEHOLDER.sub(lambda m: self._placeholder(m, values), str(event.get("message", "")))
        text = _TAG.sub("", _PROFILE.sub("", text)).strip()
        return Described(str(event.get("name", f"event {event_id}")), text, group)

    def _values(self, specs: list[dict[str, Any]], arguments: bytes) -> list[tuple[Any, str]]:
        """(raw value, rendered) per argument, read little-endian in order."""
        out: list[tuple[Any, str]] = []
        at = 0
        raw = bytes(arguments).ljust(40, b"\0")
        for spec in specs:
            type_ = str(spec.get("type", "uint8_t"))
            enum = self.enums.get(type_) or (self.enums.get(type_.rsplit("::", 1)[-1]) if "::" in type_ else None)
            base = str(enum.get("type", "uint8_t")) if enum else type_
            fmt, size = _TYPES.get(base, ("B", 1))
            if at + size > len(raw):
                out.append((None, "?"))
                continue
            value = struct.unpack_from("<" + fmt, raw, at)[0]
            at += size
            out.append((value, self._render(value, enum)))
        return out

    @staticmethod
    def _render(value: Any, enum: dict[str, Any] | None) -> str:
        if enum is None:
            return str(value)
        entries = enum.get("entries") or {}
        if enum.get("is_bitfield"):
            names = [str(e.get("description") or e.get("name")) for k, e in entries.items()
                     if int(k) and int(value) & int(k) == int(k)]
            return ", ".join(names) if names else "none"
        entry = entries.get(str(value))
        return str(entry.get("description") or entry.get("name")) if entry else str(value)

    @staticmethod
    def _placeholder(m: re.Match[str], values: list[tuple[Any, str]]) -> str:
        index = int(m.group(1)) - 1
        if not 0 <= index < len(values):
            return m.group(0)
        value, rendered = values[index]
        if isinstance(value, float):
            digits = int(m.group(2)) if m.group(2) is not None else 2
            rendered = f"{value:.{digits}f}" if math.isfinite(value) else str(value)
        unit = m.group(3).removesuffix("_v").strip()
        return f"{rendered} {unit}" if unit else rendered


# PX4's arming-check report (Report::report, src/modules/commander/HealthAndArmingChecks): the
# summary event, then each failing check and health event, then the health summary, in one
# burst, sent when the checks change (on PX4 SIH 1.15: 3.7 s before an `arm` it refused, then not
# again for 28 s). Its events, not the ones around the refusing COMMAND_ACK, say why arming fails.
ARMING_REPORT_START = "commander_arming_check_summary"
ARMING_REPORT_SUMMARIES = ("commander_arming_check_summary", "commander_health_summary")
ARMING_REPORT_BURST = 1.0  # s: the report's events follow its summary within this
ARMING_REPORT_MAX_AGE = 30.0  # s: an older report is not taken as the current reason
_SERIOUS = ("EMERGENCY", "ALERT", "CRITICAL", "ERROR", "WARNING")


def arming_report(notes: Iterable[Note], now: float,
                  max_age: float = ARMING_REPORT_MAX_AGE) -> tuple[float, tuple[str, ...]] | None:
    """The latest arming-check report within `max_age` s of `now`: (its age in s, the failing
    checks in words: its events of level WARNING or worse, each once). None: no report."""
    notes = list(notes)
    starts = [i for i, n in enumerate(notes)
              if n.source == "event" and n.name == ARMING_REPORT_START and now - max_age <= n.at <= now]
    if not starts:
        return None
    first = notes[starts[-1]]
    out: list[str] = []
    for n in notes[starts[-1] + 1:]:
        if n.at > first.at + ARMING_REPORT_BURST or n.name == ARMING_REPORT_START:
            break
        if (n.source == "event" and n.name not in ARMING_REPORT_SUMMARIES and n.level in _SERIOUS
                and n.text not in out):
            out.append(n.text)
    return now - first.at, tuple(out)


def ftp_path(uri: str) -> str:
    """The FTP path of an `mftp://` URI (`mftp://[;comp=1]etc/x` -> `etc/x`)."""
    path = uri.removeprefix("mftp://")
    if path.startswith("[") and "]" in path:
        path = path.split("]", 1)[1]
    return path


def _maybe_xz(name: str, data: bytes) -> bytes:
    if name.endswith(".xz") or data[:6] == b"\xfd7zXZ\x00":
        try:
            return lzma.decompress(data)
        except lzma.LZMAError as exc:
            raise MetadataError(f"{name}: not valid xz ({exc})") from None
    return data


def default_cache_dir() -> Path:
    """systemd's CacheDirectory= ($CACHE_DIRECTORY: the unit's sandbox has no home), else
    $XDG_CACHE_HOME/bezier-companion, else ~/.cache/bezier-companion."""
    systemd = os.environ.get("CACHE_DIRECTORY")
    if systemd:
        return Path(systemd.split(":")[0])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "bezier-companion"


class Px4Events:
    """The autopilot's events metadata for a link: loaded once per firmware, cached on disk."""

    def __init__(self, link: MavlinkLink, cache_dir: str = "") -> None:
        self.link = link
        self.cache_dir = Path(cache_dir) if cache_dir else default_cache_dir()
        self.metadata: EventsMetadata | None = None
        self.status = "the autopilot's events metadata is not loaded yet"
        self.source = ""  # "cache" | "ftp"
        self._waiters: dict[str, asyncio.Future[Any]] = {}
        self._ftp_seq = 0
        self._lock = asyncio.Lock()

    # -- decoding ------------------------------------------------------------------------------

    def describe(self, event_id: int, arguments: bytes) -> Described | None:
        return self.metadata.describe(event_id, arguments) if self.metadata is not None else None

    def unknown(self, event_id: int) -> str:
        """What to say of an event with no text: why it has none."""
        if self.metadata is None:
            return f"event {event_id} ({self.status})"
        return f"event {event_id} (not in the autopilot's events metadata)"

    # -- messages from the link (MavlinkLink.listeners) -----------------------------------------

    def on_message(self, kind: str, msg: Any) -> None:
        fut = self._waiters.get(kind)
        if fut is None or fut.done():
            return
        if kind == "FILE_TRANSFER_PROTOCOL":
            payload = bytes(msg.payload)
            seq, _, opcode, _, _, _, _, _ = _FTP_HEADER.unpack_from(payload.ljust(12, b"\0"))
            if opcode not in (OP_ACK, OP_NAK) or seq != (self._ftp_seq + 1) & 0xFFFF:
                return
        fut.set_result(msg)

    async def _wait(self, kind: str, send: Any, timeout: float) -> Any:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[Any] = loop.create_future()
        self._waiters[kind] = fut
        try:
            await send()
            return await asyncio.wait_for(fut, timeout)
        finally:
            self._waiters.pop(kind, None)

    async def _request(self, kind: str, msg_id: int) -> Any:
        """MAV_CMD_REQUEST_MESSAGE, waiting for the message itself (its ACK is not awaited, so
        that no other REQUEST_MESSAGE in flight is displaced)."""
        link = self.link

        async def send() -> None:
            link.send_message(link.conn.mav.command_long_encode(
                link.cfg.vehicle.sysid, link.cfg.vehicle.autopilot_component, MAV_CMD_REQUEST_MESSAGE, 0, msg_id,
                0, 0, 0, 0, 0, 0))
        for _ in range(2):
            with contextlib.suppress(TimeoutError):
                return await self._wait(kind, send, 1.5)
        raise MetadataError(f"the autopilot did not send {kind} when asked")

    # -- loading ---------------------------------------------------------------------------------

    async def load(self) -> bool:
        """Load the metadata (cache, else FTP); True if loaded. Failures are said, not raised."""
        async with self._lock:
            if self.metadata is not None:
                return True
            try:
                await self._load()
            except (MetadataError, OSError, ValueError) as exc:
                self.status = f"the autopilot's events metadata could not be had: {exc}"
                log.warning("PX4 events metadata: %s", exc)
                return False
            return True

    async def _load(self) -> None:
        version = await self._request("AUTOPILOT_VERSION", MSG_ID_AUTOPILOT_VERSION)
        meta = await self._request("COMPONENT_METADATA", MSG_ID_COMPONENT_METADATA)
        uri = meta.uri.decode(errors="replace") if isinstance(meta.uri, bytes) else str(meta.uri)
        key = f"px4-events-{int(version.flight_sw_version):08x}-{int(version.uid):016x}-{int(meta.file_crc):08x}"
        cached = self.cache_dir / f"{key}.json"
        if cached.is_file():
            try:
                self.metadata = EventsMetadata(json.loads(cached.read_text()))
                self.source, self.status = "cache", f"loaded from {cached}"
                log.info("PX4 events metadata: %d events from the cache %s", len(self.metadata), cached)
                return
            except (ValueError, MetadataError) as exc:
                log.warning("PX4 events metadata: cache %s unreadable (%s); fetching again", cached, exc)
        started = time.monotonic()
        if not uri.startswith("mftp://"):
            raise MetadataError(f"the general metadata is at {uri!r}, not on the autopilot (mftp://)")
        general = json.loads(_maybe_xz(uri, await self.read_file(ftp_path(uri))))
        events_uri = next((str(t.get("uri", "")) for t in general.get("metadataTypes", [])
                           if t.get("type") == COMP_METADATA_TYPE_EVENTS), "")
        if not events_uri.startswith("mftp://"):
            raise MetadataError(f"the general metadata names no events file on the autopilot ({events_uri!r})")
        data = json.loads(_maybe_xz(events_uri, await self.read_file(ftp_path(events_uri))))
        self.metadata = EventsMetadata(data)
        self.source, self.status = "ftp", f"fetched over MAVLink FTP from {events_uri}"
        log.info("PX4 events metadata: %d events over MAVLink FTP in %.1f s", len(self.metadata),
                 time.monotonic() - started)
        try:
            self.cache_dir.mkdir(parents=True, exist_ok=True)
            tmp = cached.with_suffix(f".{os.getpid()}.tmp")  # concurrent companions: one tmp each
            tmp.write_text(json.dumps(data))
            os.replace(tmp, cached)
        except OSError as exc:
            log.warning("PX4 events metadata: not cached in %s: %s", self.cache_dir, exc)

    # -- MAVLink FTP (read-only) -------------------------------------------------------------------

    async def _ftp(self, opcode: int, session: int = 0, offset: int = 0, data: bytes = b"",
                   size: int | None = None) -> tuple[int, int, bytes]:
        """One request, retried on silence: (opcode ACK/NAK, offset, data) of the answer."""
        link = self.link
        for _ in range(FTP_RETRIES):
            self._ftp_seq = (self._ftp_seq + 1) & 0xFFFF
            payload = (_FTP_HEADER.pack(self._ftp_seq, session, opcode, len(data) if size is None else size, 0, 0, 0,
                                        offset) + data).ljust(251, b"\0")

            async def send(payload: bytes = payload) -> None:
                link.send_message(link.conn.mav.file_transfer_protocol_encode(
                    0, link.cfg.vehicle.sysid, link.cfg.vehicle.autopilot_component, list(payload)))
            try:
                msg = await self._wait("FILE_TRANSFER_PROTOCOL", send, FTP_TIMEOUT)
            except TimeoutError:
                continue
            raw = bytes(msg.payload).ljust(251, b"\0")
            _, _, op, n, _, _, _, at = _FTP_HEADER.unpack_from(raw)
            return op, at, raw[12:12 + min(n, FTP_DATA_MAX)]
        raise MetadataError(f"no answer to MAVLink FTP opcode {opcode} after {FTP_RETRIES} tries")

    async def read_file(self, path: str) -> bytes:
        op, _, data = await self._ftp(OP_OPEN_RO, data=path.encode())
        if op != OP_ACK:
            raise MetadataError(f"MAVLink FTP could not open {path!r} (error {data[:1].hex() or '?'})")
        size = struct.unpack_from("<I", data.ljust(4, b"\0"))[0]
        if size > FTP_MAX_FILE:
            raise MetadataError(f"{path!r} is {size} bytes, more than {FTP_MAX_FILE}")
        out = bytearray()
        try:
            while len(out) < size:
                op, at, chunk = await self._ftp(OP_READ, offset=len(out), size=FTP_DATA_MAX)
                if op == OP_NAK and chunk[:1] == bytes([ERR_EOF]):
                    break
                if op != OP_ACK or at != len(out) or not chunk:
                    raise MetadataError(f"MAVLink FTP read of {path!r} failed at byte {len(out)}")
                out += chunk
        finally:
            with contextlib.suppress(MetadataError):
                await self._ftp(OP_TERMINATE)
        if len(out) != size:
            raise MetadataError(f"MAVLink FTP read {len(out)} of {size} bytes of {path!r}")
        return bytes(out)
