"""A rejected inbound message and the payload markers the decoder shares: one definition, used by
the JSON parser (companion.wire.jsonparse) and the message decoder (companion.wire.messages)."""

from __future__ import annotations

from typing import Any

from planner_core import FieldError

MAX_QUOTE = 100  # characters of a peer's value quoted back in a reason
MAX_REASON = 400  # characters of a reason; a field path is cut to MAX_QUOTE


def quote(value: Any, n: int = MAX_QUOTE) -> str:
    """repr() of a peer's value, at most about n characters (the length said when cut)."""
    text = value if isinstance(value, str) and value.startswith(("'", '"')) else repr(value)
    return text if len(text) <= n else f"{text[: n - 1]}… ({len(text)} chars)"


def bounded(text: str, n: int) -> str:
    """text, at most about n characters (the length said when cut)."""
    return text if len(text) <= n else f"{text[: n - 15]}… ({len(text)} chars)"


class MessageError(FieldError):
    """A rejected message; `field` is a JSON path ('' for the whole payload). Both are cut to a
    bounded length here, whatever the caller passed: a peer must not inflate the events."""

    def __init__(self, field: str, reason: str) -> None:
        field, reason = bounded(str(field), MAX_QUOTE), bounded(str(reason), MAX_REASON)
        super().__init__(field, reason)
        self.args = (f"{field or 'payload'}: {reason}",)


class InternalError(MessageError):
    """`read` met something it did not foresee (a bug): the message is rejected, and the
    service also reports an `error` event."""


class Oversized:
    """A payload too large to take: only its size is known (it was never read whole)."""

    __slots__ = ("size",)

    def __init__(self, size: int) -> None:
        self.size = int(size)

    def __len__(self) -> int:
        return self.size

    def __repr__(self) -> str:
        return f"Oversized({self.size})"
