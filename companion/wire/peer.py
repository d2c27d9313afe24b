"""Who the companion listens to on the MAVLink link: one autopilot, authenticated.

The link is bound to the autopilot's system and component id (`[vehicle] sysid`,
`autopilot_component`) and, on UDP, to the address its first autopilot HEARTBEAT came from
(MAV_TYPE not a GCS or an onboard controller, autopilot field not INVALID). Everything else
is ignored and counted, never acted on: another address, another id, and, with a signing key
and `[mavlink] require_signed_inbound`, an unsigned or wrongly signed message.

With `udpout:HOST:PORT` the address is the configured destination from the start (pinned).
Re-binding (udpin): the autopilot's address may change legitimately (mavlink-router restarted, a new
UDP source port). The link re-binds to a new address only when the bound one has been silent
for `[mavlink] link_timeout` AND the new address sends an autopilot HEARTBEAT with the bound
ids (signed, when signing is required). A reboot of the autopilot keeps its ids and address:
the binding simply survives it.

Signatures follow https://mavlink.io/en/guide/message_signing.html: a timestamp (10 µs since
2015-01-01) per stream (link id, system, component) that must increase, and a new stream
accepted only when its timestamp is at most one minute behind ours. Unlike pymavlink's own
check, a stream's timestamp is recorded only for a message whose signature is good: a forged
packet with a huge timestamp cannot lock the autopilot's stream out.
"""

from __future__ import annotations

import hashlib
import math
import struct
import time
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

# MAV_TYPEs that are not an autopilot (a heartbeat from them never binds the link)
NOT_AUTOPILOT = frozenset({
    mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_TYPE_GIMBAL, mavlink.MAV_TYPE_ADSB,
    mavlink.MAV_TYPE_CAMERA, mavlink.MAV_TYPE_ANTENNA_TRACKER,
})
EPOCH_2015 = 1420070400  # the signing timestamp's epoch (Unix time of 2015-01-01)
NEW_STREAM_WINDOW = 6_000_000  # 10 µs units: one minute (the spec's rule for a new stream)

# Why a message was ignored (the keys of `PeerGate.ignored`)
OTHER_ADDRESS = "other_address"  # from a UDP address other than the bound autopilot's
OTHER_ID = "other_id"  # from another system or component id
UNSIGNED = "unsigned"  # not signed, or not signed with our key (signing required)
UNBOUND = "before_binding"  # before any autopilot heartbeat bound the link


def signing_now() -> int:
    """The current time as a signing timestamp (10 µs units since 2015-01-01)."""
    return int(max(time.time() - EPOCH_2015, 0.0) * 100_000)


class SignatureCheck:
    """MAVLink.check_signature's replacement (same signature): the spec's rules, and the stream
    timestamp recorded only once the signature is known good."""

    _unpack = struct.Struct("<IH").unpack

    def __init__(self, mav: Any) -> None:
        self.mav = mav
        self.streams: dict[tuple[int, int, int], int] = {}
        self.replayed = 0  # good signature, timestamp not newer than the stream's last
        self.stale = 0  # a new stream more than a minute behind our clock

    def __call__(self, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        signing = self.mav.signing
        key = signing.secret_key
        if key is None:
            return False
        h = hashlib.sha256()
        h.update(key)
        h.update(msgbuf[:-6])
        if h.digest()[:6] != bytes(msgbuf[-6:]):
            return False
        lo, hi = self._unpack(bytes(msgbuf[-12:-6]))
        stamp = lo + (hi << 32)
        stream = (int(msgbuf[-13]), src_system, src_component)
        last = self.streams.get(stream)
        if last is not None:
            if stamp <= last:
                self.replayed += 1
                return False
        elif stamp + NEW_STREAM_WINDOW < max(signing.timestamp, signing_now()):
            self.stale += 1
            return False
        if last is None and len(self.streams) >= 64:  # bounded: only key holders get here
            self.streams.pop(next(iter(self.streams)))
        self.streams[stream] = stamp
        signing.timestamp = max(signing.timestamp, stamp)
        return True


@dataclass
class PeerGate:
    """The binding and the verdict on each message. `address` None: not bound yet (UDP) or
    not applicable (serial, TCP: point to point)."""

    sysid: int
    compid: int
    udp: bool
    require_signed: bool
    link_timeout: float
    address: tuple[str, int] | None = None
    pinned: bool = False  # udpout: the address is the configured destination, never re-bound
    bound: bool = False
    last_heard: float = -math.inf  # the bound autopilot's last accepted message (monotonic)
    ignored: dict[str, int] = field(default_factory=dict)
    rebinds: list[tuple[tuple[str, int] | None, tuple[str, int]]] = field(default_factory=list)

    def _ignore(self, why: str) -> str:
        self.ignored[why] = self.ignored.get(why, 0) + 1
        return why

    def address_ok(self, addr: tuple[str, int] | None, now: float) -> bool:
        """Whether a datagram from `addr` is worth parsing: the bound address, or any while
        unbound or while the bound autopilot has been silent for link_timeout (a re-bind)."""
        if not self.udp or addr == self.address or not (self.bound or self.pinned):
            return True
        if not self.pinned and now - self.last_heard > self.link_timeout:
            return True
        self._ignore(OTHER_ADDRESS)
        return False

    def admit(self, msg: Any, addr: tuple[str, int] | None, now: float) -> str | None:
        """None: the message is the bound autopilot's, act on it; else why it is ignored."""
        if msg.get_srcSystem() != self.sysid or msg.get_srcComponent() != self.compid:
            return self._ignore(OTHER_ID)
        if self.require_signed and not msg.get_signed():
            return self._ignore(UNSIGNED)
        is_autopilot = (msg.get_type() == "HEARTBEAT" and msg.type not in NOT_AUTOPILOT
                        and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID)
        if self.udp and (not self.bound or addr != self.address):
            silent = now - self.last_heard > self.link_timeout
            if self.pinned and addr != self.address:
                return self._ignore(OTHER_ADDRESS)
            if not is_autopilot or (self.bound and not silent):
                return self._ignore(OTHER_ADDRESS if self.bound else UNBOUND)
            if self.bound and addr is not None:
                self.rebinds = [*self.rebinds[-7:], (self.address, addr)]
            self.address = addr
        elif not self.bound and not is_autopilot:
            return self._ignore(UNBOUND)
        self.bound = True
        self.last_heard = now
        return None
