"""MAVLink's EVENT (410) and COMPONENT_METADATA (397) for pymavlink dialects that lack them, and PX4's event ids.

PX4 >= 1.14 reports arming, takeoff, failsafes, landing, disarming and refusals as EVENT
messages, not STATUSTEXT. The pymavlink in use does not define EVENT, so `install()` adds a
message class, built from the XML definition below with pymavlink's own generator code (field
ordering and CRC_EXTRA), to the v20 dialect modules that connections decode with: `common`
(the mock), `all` (what `mavutil.mavlink_connection` picks under MAVLINK20) and any other v20
dialect already imported. A dialect that already defines EVENT is left alone.

The 40 argument bytes are event-specific (PX4's component metadata describes them); this
module carries them raw and names the ids it knows in `PX4_EVENTS`.
"""

from __future__ import annotations

import struct
import sys
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from types import ModuleType
from typing import Any, NamedTuple

from pymavlink.generator import mavgen_python, mavparse

MSG_ID_EVENT = 410
ARGUMENTS_LEN = 40

# The definition from MAVLink's message_definitions (common.xml, formerly development.xml),
# fields in XML order; descriptions trimmed.
EVENT_XML = """
<message id="410" name="EVENT">
  <field type="uint8_t" name="destination_component">Component ID</field>
  <field type="uint8_t" name="destination_system">System ID</field>
  <field type="uint32_t" name="id">Event ID (as defined in the component metadata)</field>
  <field type="uint32_t" name="event_time_boot_ms" units="ms">Timestamp (time since boot).</field>
  <field type="uint16_t" name="sequence">Sequence number.</field>
  <field type="uint8_t" name="log_levels">4 bits MSB: internal, 4 bits LSB: external.</field>
  <field type="uint8_t[40]" name="arguments">Arguments (depend on event ID).</field>
</message>
"""

MSG_ID_COMPONENT_METADATA = 397
COMPONENT_METADATA_XML = """
<message id="397" name="COMPONENT_METADATA">
  <field type="uint32_t" name="time_boot_ms" units="ms">Timestamp (time since system boot).</field>
  <field type="uint32_t" name="file_crc">CRC32 of the general metadata file.</field>
  <field type="char[100]" name="uri">MAVLink FTP URI for the general metadata file (may be xz compressed).</field>
</message>
"""

# Log levels of the EVENT log_levels nibbles (the MAVLink events protocol; 0-7 match
# MAV_SEVERITY).
LEVELS: dict[int, str] = {
    0: "EMERGENCY",
    1: "ALERT",
    2: "CRITICAL",
    3: "ERROR",
    4: "WARNING",
    5: "NOTICE",
    6: "INFO",
    7: "DEBUG",
    8: "PROTOCOL",
    9: "DISABLED",
}
LEVEL_IDS: dict[str, int] = {name: level for level, name in LEVELS.items()}


def px4_event_id(name: str) -> int:
    """PX4's `events::ID(name)`: 24-bit FNV-1a of the name, autopilot component in the top byte."""
    h = 0x811C9DC5
    for byte in name.encode("ascii"):
        h = ((h ^ byte) * 0x01000193) & 0xFFFFFFFF
    return (h & 0xFFFFFF) | (1 << 24)


# The events the mock's PX4 flavour emits: PX4's own names (commander, navigator and the
# health/arming checks, PX4 1.14/1.15), so the ids are PX4's; "mock_" names are the mock's own,
# for refusals PX4 words differently.
_PX4_EVENT_NAMES = (
    "commander_armed_by",  # args: uint8 arm_disarm_reason_t
    "commander_disarmed_by",  # args: uint8 arm_disarm_reason_t
    "commander_disarm_denied_not_landed",
    "commander_takeoff_detected",
    "commander_landing_detected",
    "commander_failsafe_enter_generic",  # args: uint32 user mode (custom_mode), uint8 action
    "commander_modeswitch_not_avail",  # args: uint32 custom_mode of the refused mode, uint8 nav mode
    "check_modes_offboard_no_signal",
    "check_modes_offboard_signal_lost",
    "check_rc_dl_no_dllink",  # "No connection to the ground control station"
    "navigator_takeoff_default_alt",  # args: float altitude (m)
    "mock_arm_denied_mode",  # arming refused in a mode that cannot arm
    "mock_takeoff_denied_alt",  # NAV_TAKEOFF altitude at or below home
)
PX4_EVENTS: dict[int, str] = {px4_event_id(n): n for n in _PX4_EVENT_NAMES}
PX4_EVENT_IDS: dict[str, int] = {n: i for i, n in PX4_EVENTS.items()}


class EventInfo(NamedTuple):
    id: int
    level: str
    name: str | None


class _Layout(NamedTuple):
    fieldnames: list[str]
    ordered_fieldnames: list[str]
    fieldtypes: list[str]
    fmtstr: str
    native_fmtstr: str
    orders: list[int]
    lengths: list[int]
    array_lengths: list[int]
    crc_extra: int


def _layout(xml: str = EVENT_XML) -> _Layout:
    """Wire layout and CRC_EXTRA of a message definition, computed as pymavlink's generator does."""
    root = ET.fromstring(xml)
    msg = mavparse.MAVType(root.attrib["name"], root.attrib["id"], 0)
    for f in root.iter("field"):
        msg.fields.append(mavparse.MAVField(f.attrib["name"], f.attrib["type"], None, None))
        msg.fieldnames.append(f.attrib["name"])
    # mavparse sorts base fields by element size, largest first (a stable sort).
    msg.ordered_fields = sorted(msg.fields, key=lambda f: f.type_length, reverse=True)
    crc_extra = mavparse.message_checksum(msg)
    fieldnames = [f.name for f in msg.fields]
    ordered = [f.name for f in msg.ordered_fields]
    fieldlengths = [f.array_length or 1 for f in msg.fields]
    orders = [ordered.index(n) for n in fieldnames]
    lengths = [0] * len(fieldnames)
    for i, n in enumerate(orders):
        lengths[n] = fieldlengths[i]
    return _Layout(
        fieldnames=fieldnames,
        ordered_fieldnames=ordered,
        fieldtypes=[f.type for f in msg.fields],
        fmtstr="<" + "".join(mavgen_python.mavfmt(f) for f in msg.ordered_fields),
        native_fmtstr="<" + "".join(mavgen_python.native_mavfmt(f) for f in msg.ordered_fields),
        orders=orders,
        lengths=lengths,
        array_lengths=[f.array_length for f in msg.ordered_fields],
        crc_extra=crc_extra,
    )


_LAYOUT = _layout()
CRC_EXTRA = _LAYOUT.crc_extra
_METADATA_LAYOUT = _layout(COMPONENT_METADATA_XML)


def _metadata_class(mod: ModuleType) -> type:
    """COMPONENT_METADATA, decoded by pymavlink's own MAVLink.decode (fields in XML order)."""
    base: Any = mod.MAVLink_message
    lay = _METADATA_LAYOUT

    def __init__(self: Any, time_boot_ms: int, file_crc: int, uri: bytes | str) -> None:
        base.__init__(self, MSG_ID_COMPONENT_METADATA, "COMPONENT_METADATA")
        self._fieldnames = lay.fieldnames
        self._instance_field = None
        self._instance_offset = -1
        self.time_boot_ms = time_boot_ms
        self.file_crc = file_crc
        self.uri = uri.decode(errors="replace") if isinstance(uri, bytes) else uri

    def pack(self: Any, mav: Any, force_mavlink1: bool = False) -> bytes:
        payload = struct.pack(lay.fmtstr, self.time_boot_ms, self.file_crc, self.uri.encode())
        return bytes(base._pack(self, mav, lay.crc_extra, payload, force_mavlink1=force_mavlink1))

    attrs: dict[str, Any] = {
        "__doc__": "COMPONENT_METADATA (397): where the component's general metadata file is.",
        "__init__": __init__, "pack": pack, "id": MSG_ID_COMPONENT_METADATA, "msgname": "COMPONENT_METADATA",
        "fieldnames": lay.fieldnames, "ordered_fieldnames": lay.ordered_fieldnames, "fieldtypes": lay.fieldtypes,
        "fielddisplays_by_name": {}, "fieldenums_by_name": {}, "fieldunits_by_name": {"time_boot_ms": "ms"},
        "native_format": bytearray(lay.native_fmtstr, "ascii"), "orders": lay.orders, "lengths": lay.lengths,
        "array_lengths": lay.array_lengths, "crc_extra": lay.crc_extra, "unpacker": struct.Struct(lay.fmtstr),
        "instance_field": None, "instance_offset": -1, "_project_dialect": True,
    }
    return type("MAVLink_component_metadata_message", (base,), attrs)


def _message_class(mod: ModuleType) -> type:
    base: Any = mod.MAVLink_message
    lay = _LAYOUT

    def __init__(
        self: Any,
        destination_component: int,
        destination_system: int,
        id: int,
        event_time_boot_ms: int,
        sequence: int,
        log_levels: int,
        arguments: Sequence[int],
    ) -> None:
        base.__init__(self, MSG_ID_EVENT, "EVENT")
        self._fieldnames = lay.fieldnames
        self._instance_field = None
        self._instance_offset = -1
        self.destination_component = destination_component
        self.destination_system = destination_system
        self.id = id
        self.event_time_boot_ms = event_time_boot_ms
        self.sequence = sequence
        self.log_levels = log_levels
        self.arguments = list(arguments)

    def pack(self: Any, mav: Any, force_mavlink1: bool = False) -> bytes:
        values: list[int] = []
        for name in lay.ordered_fieldnames:
            v = getattr(self, name)
            if name == "arguments":
                values.extend(v)
            else:
                values.append(v)
        payload = struct.pack(lay.fmtstr, *values)
        return bytes(base._pack(self, mav, lay.crc_extra, payload, force_mavlink1=force_mavlink1))

    attrs: dict[str, Any] = {
        "__doc__": "EVENT (410): an event of the MAVLink events protocol.",
        "__init__": __init__,
        "pack": pack,
        "id": MSG_ID_EVENT,
        "msgname": "EVENT",
        "fieldnames": lay.fieldnames,
        "ordered_fieldnames": lay.ordered_fieldnames,
        "fieldtypes": lay.fieldtypes,
        "fielddisplays_by_name": {},
        "fieldenums_by_name": {},
        "fieldunits_by_name": {"event_time_boot_ms": "ms"},
        "native_format": bytearray(lay.native_fmtstr, "ascii"),
        "orders": lay.orders,
        "lengths": lay.lengths,
        "array_lengths": lay.array_lengths,
        "crc_extra": lay.crc_extra,
        "unpacker": struct.Struct(lay.fmtstr),
        "instance_field": None,
        "instance_offset": -1,
        "_project_dialect": True,
    }
    return type("MAVLink_event_message", (base,), attrs)


def _install_into(mod: ModuleType) -> None:
    if mod.mavlink_map.get(MSG_ID_COMPONENT_METADATA) is None:
        meta = _metadata_class(mod)
        mod.mavlink_map[MSG_ID_COMPONENT_METADATA] = meta
        setattr(mod, "MAVLINK_MSG_ID_COMPONENT_METADATA", MSG_ID_COMPONENT_METADATA)  # noqa: B010
    existing = mod.mavlink_map.get(MSG_ID_EVENT)
    if existing is not None:
        return  # ours already, or the dialect defines EVENT itself
    cls = _message_class(mod)
    mod.mavlink_map[MSG_ID_EVENT] = cls
    setattr(mod, "MAVLink_event_message", cls)  # noqa: B010 - a module attribute added at run time
    setattr(mod, "MAVLINK_MSG_ID_EVENT", MSG_ID_EVENT)  # noqa: B010


def install() -> None:
    """Make EVENT decodable and encodable in pymavlink's v20 dialects (idempotent).

    Does not import `mavutil` (importing it fixes MAVLink 1 vs 2 from the environment);
    if it is already imported, its current dialect gets EVENT too.
    """
    from pymavlink.dialects.v20 import all as v20_all
    from pymavlink.dialects.v20 import common as v20_common

    targets: dict[str, ModuleType] = {m.__name__: m for m in (v20_common, v20_all)}
    for name, mod in list(sys.modules.items()):
        if name.startswith("pymavlink.dialects.v20.") and hasattr(mod, "mavlink_map"):
            targets[name] = mod
    mavutil = sys.modules.get("pymavlink.mavutil")
    current = getattr(mavutil, "mavlink", None) if mavutil is not None else None
    if isinstance(current, ModuleType) and ".v20." in current.__name__:
        targets[current.__name__] = current
    for mod in targets.values():
        _install_into(mod)


def _dialect_of(mav: Any) -> ModuleType:
    mod = sys.modules[type(mav).__module__]
    if MSG_ID_EVENT not in mod.mavlink_map:
        install()
        _install_into(mod)
    return mod


def log_levels(level: str | int, internal: str | int | None = None) -> int:
    """The log_levels byte: external level in the low nibble, internal in the high one."""
    ext = LEVEL_IDS[level] if isinstance(level, str) else int(level)
    inn = ext if internal is None else (LEVEL_IDS[internal] if isinstance(internal, str)
                                        else int(internal))
    if not (0 <= ext <= 15 and 0 <= inn <= 15):
        raise ValueError(f"log level out of range: external {ext}, internal {inn}")
    return (inn << 4) | ext


def event_encode(
    mav: Any,
    event_id: int,
    level: str | int,
    *,
    sequence: int,
    time_boot_ms: int,
    arguments: bytes = b"",
    internal_level: str | int | None = None,
    destination_system: int = 0,
    destination_component: int = 0,
) -> Any:
    """An EVENT message object for `mav` (a pymavlink `MAVLink` of a v20 dialect)."""
    if len(arguments) > ARGUMENTS_LEN:
        raise ValueError(f"EVENT arguments are at most {ARGUMENTS_LEN} bytes, got {len(arguments)}")
    cls = _dialect_of(mav).mavlink_map[MSG_ID_EVENT]
    args = list(arguments) + [0] * (ARGUMENTS_LEN - len(arguments))
    return cls(
        destination_component,
        destination_system,
        event_id & 0xFFFFFFFF,
        time_boot_ms & 0xFFFFFFFF,
        sequence & 0xFFFF,
        log_levels(level, internal_level),
        args,
    )


def event_send(mav: Any, event_id: int, level: str | int, **kwargs: Any) -> None:
    """Encode an EVENT (see `event_encode`) and send it on `mav` (signed if `mav` signs)."""
    mav.send(event_encode(mav, event_id, level, **kwargs))


def decode_event(msg: Any) -> EventInfo:
    """(id, external level name, PX4 event name or None) of a received EVENT message."""
    if msg.get_type() != "EVENT":
        raise ValueError(f"not an EVENT message: {msg.get_type()}")
    level = int(msg.log_levels) & 0x0F
    return EventInfo(int(msg.id), LEVELS.get(level, f"LEVEL_{level}"), PX4_EVENTS.get(int(msg.id)))


def event_arguments(msg: Any) -> bytes:
    """The raw 40 argument bytes of a received EVENT (little-endian, event-specific)."""
    return bytes(msg.arguments) + bytes(ARGUMENTS_LEN - len(msg.arguments))
