"""MAVLink 2 signing for the mock: the key file and the checks on what it receives.

The signature (https://mavlink.io/en/guide/message_signing.html) is the first 48 bits of
SHA-256(secret_key + header + payload + CRC + link_id + timestamp); pymavlink's parser computes
and checks it once `setup_receive` gave it the key. With a key, the messages in SIGNED_ONLY are
dropped unless signed with it (as PX4 and ArduPilot with signing on treat commands and
setpoints); others may come unsigned. `tests/mock/test_mock_wire_spec.py` checks this against a
published signed frame and against signatures computed with hashlib from the spec.
"""

from __future__ import annotations

from typing import Any

from pymavlink.dialects.v20 import common as mav

KEY_LEN = 32

SIGNED_ONLY = frozenset({
    mav.MAVLINK_MSG_ID_COMMAND_LONG, mav.MAVLINK_MSG_ID_COMMAND_INT, mav.MAVLINK_MSG_ID_SET_MODE,
    mav.MAVLINK_MSG_ID_SET_POSITION_TARGET_LOCAL_NED, mav.MAVLINK_MSG_ID_SET_POSITION_TARGET_GLOBAL_INT,
    mav.MAVLINK_MSG_ID_PARAM_SET, mav.MAVLINK_MSG_ID_REQUEST_DATA_STREAM,
    mav.MAVLINK_MSG_ID_FILE_TRANSFER_PROTOCOL,
})


def read_signing_key(path: str) -> bytes:
    """A key file: 32 raw bytes, or 64 hex digits (surrounding whitespace ignored). Any other
    shape is an OSError naming the file."""
    with open(path, "rb") as fh:
        raw = fh.read()
    text = raw.strip()
    if len(text) == 2 * KEY_LEN:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    if len(raw) == KEY_LEN:
        return raw
    raise OSError(f"{path}: a signing key is {KEY_LEN} bytes (raw) or {2 * KEY_LEN} hex digits, got {len(raw)} bytes")


def setup_receive(parser: Any, key: bytes) -> None:
    """Make a pymavlink `MAVLink` parser check signatures with `key`: a signed packet with a
    wrong signature is dropped, an unsigned one only if its id is in SIGNED_ONLY."""
    if len(key) != KEY_LEN:
        raise ValueError(f"signing key: {KEY_LEN} bytes expected, got {len(key)}")
    parser.signing.secret_key = bytes(key)
    parser.signing.allow_unsigned_callback = lambda _mav, msg_id: msg_id not in SIGNED_ONLY
