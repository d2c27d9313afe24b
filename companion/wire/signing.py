"""MAVLink 2 signing keys as files hold them (shared by the companion and the mock autopilot)."""

from __future__ import annotations


def read_signing_key(path: str) -> bytes:
    """A MAVLink 2 signing key from a file: 32 raw bytes, or 64 hex digits (whitespace ignored).
    A file of any other shape is an OSError naming the path."""
    with open(path, "rb") as fh:
        raw = fh.read()
    text = raw.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    if len(raw) == 32:
        return raw
    raise OSError(f"{path}: a signing key is 32 bytes (raw) or 64 hex digits, got {len(raw)} bytes")
