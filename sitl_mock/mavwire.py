"""The MAVLink 2 messages the mock sends that pymavlink's bundled `common` dialect lacks.

EVENT (410) and COMPONENT_METADATA (397), written from their definitions in MAVLink's
message_definitions (common.xml; EVENT was in development.xml before), laid out and
checksummed as the MAVLink serialization guide says (https://mavlink.io/en/guide/serialization.html):
fields on the wire sorted by type size, largest first (stable), and CRC_EXTRA the X.25 CRC of
"NAME " and each wire field's "type name " (plus the array length byte), folded to one byte.
pymavlink's `MAVLink_message._pack` does the framing (header, payload truncation, CRC,
signing), as for every other message the mock sends. Nothing here comes from the companion: the
two sides encode and decode independently, and `tests/mock/test_mock_wire_spec.py` checks
these bytes against the published C headers' sizes, offsets and CRC_EXTRA.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mav

_SIZES = {"char": 1, "uint8_t": 1, "int8_t": 1, "uint16_t": 2, "int16_t": 2, "uint32_t": 4, "int32_t": 4,
          "float": 4, "uint64_t": 8, "int64_t": 8, "double": 8}
_FORMATS = {"char": "s", "uint8_t": "B", "int8_t": "b", "uint16_t": "H", "int16_t": "h", "uint32_t": "I",
            "int32_t": "i", "float": "f", "uint64_t": "Q", "int64_t": "q", "double": "d"}


def x25_crc(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/MCRF4XX, MAVLink's checksum (the serialization guide's `crc_accumulate`)."""
    for byte in data:
        tmp = byte ^ (crc & 0xFF)
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return crc


@dataclass(frozen=True)
class Field:
    type: str  # the XML type without its array suffix: "uint8_t", "char", ...
    name: str
    array: int = 0  # 0: a scalar


@dataclass(frozen=True)
class MessageDef:
    id: int
    name: str
    fields: tuple[Field, ...]  # in XML order (none of these two has extension fields)

    @property
    def wire_fields(self) -> tuple[Field, ...]:
        return tuple(sorted(self.fields, key=lambda f: _SIZES[f.type], reverse=True))

    @property
    def length(self) -> int:
        return sum(_SIZES[f.type] * max(1, f.array) for f in self.fields)

    @property
    def crc_extra(self) -> int:
        text = (self.name + " ").encode()
        for f in self.wire_fields:
            text += (f.type + " " + f.name + " ").encode()
            if f.array:
                text += bytes([f.array])
        crc = x25_crc(text)
        return (crc & 0xFF) ^ (crc >> 8)

    def payload(self, values: dict[str, Any]) -> bytes:
        out = b""
        for f in self.wire_fields:
            v = values[f.name]
            if f.type == "char":
                raw = v.encode() if isinstance(v, str) else bytes(v)
                if len(raw) > max(1, f.array):
                    raise ValueError(f"{self.name}.{f.name}: at most {f.array} bytes, got {len(raw)}")
                out += raw.ljust(max(1, f.array), b"\0")
            elif f.array:
                items = list(v) + [0] * (f.array - len(v))
                if len(items) != f.array:
                    raise ValueError(f"{self.name}.{f.name}: at most {f.array} items, got {len(v)}")
                out += struct.pack(f"<{f.array}{_FORMATS[f.type]}", *items)
            else:
                out += struct.pack("<" + _FORMATS[f.type], v)
        return out


EVENT = MessageDef(410, "EVENT", (
    Field("uint8_t", "destination_component"),
    Field("uint8_t", "destination_system"),
    Field("uint32_t", "id"),
    Field("uint32_t", "event_time_boot_ms"),
    Field("uint16_t", "sequence"),
    Field("uint8_t", "log_levels"),
    Field("uint8_t", "arguments", 40),
))
COMPONENT_METADATA = MessageDef(397, "COMPONENT_METADATA", (
    Field("uint32_t", "time_boot_ms"),
    Field("uint32_t", "file_crc"),
    Field("char", "uri", 100),
))


class Outgoing(mav.MAVLink_message):  # type: ignore[misc]
    """A message of a `MessageDef`, sendable with pymavlink's `MAVLink.send` (framed, signed)."""

    def __init__(self, definition: MessageDef, **values: Any) -> None:
        super().__init__(definition.id, definition.name)
        self.definition = definition
        self._fieldnames = [f.name for f in definition.fields]
        self._raw = definition.payload(values)
        for name, value in values.items():
            setattr(self, name, value)

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        return bytes(self._pack(mav, self.definition.crc_extra, self._raw, force_mavlink1=force_mavlink1))


def event(event_id: int, log_levels: int, sequence: int, time_boot_ms: int, arguments: bytes = b"") -> Outgoing:
    if len(arguments) > 40:
        raise ValueError(f"EVENT arguments are at most 40 bytes, got {len(arguments)}")
    return Outgoing(EVENT, destination_component=0, destination_system=0, id=event_id & 0xFFFFFFFF,
                    event_time_boot_ms=time_boot_ms & 0xFFFFFFFF, sequence=sequence & 0xFFFF,
                    log_levels=log_levels & 0xFF, arguments=list(arguments))


def component_metadata(time_boot_ms: int, file_crc: int, uri: str) -> Outgoing:
    return Outgoing(COMPONENT_METADATA, time_boot_ms=time_boot_ms & 0xFFFFFFFF, file_crc=file_crc & 0xFFFFFFFF,
                    uri=uri)
