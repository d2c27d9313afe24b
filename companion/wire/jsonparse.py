"""Inbound JSON, parsed within the limits a peer must not exceed: size, number length, duplicate
keys (each named by its JSON path), nesting depth, then one walk over the values (finite, within
[limits] max_number, strings and arrays bounded). The first step of companion.wire.messages."""

from __future__ import annotations

import json
import math
from typing import Any

from companion.config import LimitsConfig
from companion.wire.errors import MAX_QUOTE, MessageError, Oversized, quote


def json_path(parts: Any) -> str:
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


class _LongNumber(Exception):
    def __init__(self, literal: str) -> None:
        super().__init__(literal[:MAX_QUOTE])
        self.literal = literal


def _converters(max_chars: int) -> tuple[Any, Any]:
    """json.loads hooks that see each number's literal before it is converted."""

    def to_int(s: str) -> int:
        if len(s) > max_chars:
            raise _LongNumber(s)
        return int(s)

    def to_float(s: str) -> float:
        if len(s) > max_chars:
            raise _LongNumber(s)
        return float(s)

    return to_int, to_float


class _DuplicateKey(Exception):
    pass


def _unique_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """object_pairs_hook: a dict, or _DuplicateKey when a key is given twice (json.loads would
    keep the last silently: `{"add": [obstacle], "add": []}` would drop the obstacle)."""
    out = dict(pairs)
    if len(out) != len(pairs):
        raise _DuplicateKey
    return out


class _Marked(dict[str, Any]):
    """A parsed object that repeats `dup` (only built to find where a duplicate is)."""

    dup: str = ""


def _marking_pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    seen: set[str] = set()
    for k, _ in pairs:
        if k in seen:
            out = _Marked(pairs)
            out.dup = k
            return out
        seen.add(k)
    return dict(pairs)


def _duplicate_path(text: str, to_int: Any, to_float: Any) -> tuple[str, str]:
    """The JSON path and name of the first repeated key (parsed again: only for a message that has one)."""
    doc = json.loads(text, parse_int=to_int, parse_float=to_float, object_pairs_hook=_marking_pairs)
    stack: list[tuple[Any, tuple[Any, ...]]] = [(doc, ())]
    while stack:
        node, path = stack.pop()
        if isinstance(node, _Marked):
            return json_path((*path, node.dup)), node.dup
        if isinstance(node, dict):
            stack.extend((v, (*path, k)) for k, v in reversed(list(node.items())))
        elif isinstance(node, list):
            stack.extend((v, (*path, i)) for i, v in reversed(list(enumerate(node))))
    return "", ""  # pragma: no cover - called only when a duplicate was seen


def parse_json(payload: bytes | Oversized, max_bytes: int, max_number_chars: int = 32) -> Any:
    if len(payload) > max_bytes or isinstance(payload, Oversized):
        raise MessageError("", f"payload of {len(payload)} bytes exceeds the limit of {max_bytes} "
                               "([limits] max_message_bytes)")
    try:
        text = payload.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MessageError("", f"not UTF-8: {exc.reason} at byte {exc.start}") from None
    to_int, to_float = _converters(max_number_chars)
    try:
        return json.loads(text, parse_int=to_int, parse_float=to_float, object_pairs_hook=_unique_pairs)
    except _DuplicateKey:
        where, key = _duplicate_path(text, to_int, to_float)
        raise MessageError(where, f"key {quote(key, 40)} appears more than once in the same object: which one "
                                  "was meant is ambiguous (duplicate keys are refused)") from None
    except json.JSONDecodeError as exc:
        raise MessageError("", f"malformed JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    except _LongNumber as exc:
        at = text.find(exc.literal)
        line = text.count("\n", 0, at) + 1
        col = at - (text.rfind("\n", 0, at) + 1) + 1
        raise MessageError("", f"a number of {len(exc.literal)} characters ({quote(exc.literal[:40] + '…', 60)}) "
                               f"at line {line} column {col} is longer than {max_number_chars} "
                               "([limits] max_number_chars)") from None
    except RecursionError:
        raise MessageError("", "nested too deeply to parse ([limits] max_depth)") from None
    except ValueError as exc:  # anything else the parser refuses
        raise MessageError("", f"malformed JSON: {quote(str(exc))}") from None


def check_values(obj: Any, lim: LimitsConfig) -> None:
    """One walk over a parsed message, without recursion: nesting depth, string and key
    lengths, array lengths, and every number finite and within [limits] max_number.

    NaN, Infinity and overflowing literals (1e999) parse to floats; they are named here.
    """
    longest = max(("max_waypoints", "max_obstacles", "max_obstacle_vertices", "max_obstacle_planes"),
                  key=lambda n: int(getattr(lim, n)))
    max_len = int(getattr(lim, longest))
    max_num, max_str, max_depth = lim.max_number, lim.max_string_chars, lim.max_depth
    stack: list[tuple[Any, tuple[Any, ...]]] = [(obj, ())]
    while stack:
        node, path = stack.pop()
        if len(path) > max_depth:
            raise MessageError(json_path(path), f"nested deeper than {max_depth} levels ([limits] max_depth)")
        t = type(node)
        if t is float or t is int:
            if not math.isfinite(node):
                raise MessageError(json_path(path), f"non-finite number {node} is not allowed")
            if abs(node) > max_num:
                raise MessageError(json_path(path), f"{quote(node, 40)} is larger in magnitude than {max_num:g} "
                                                    "([limits] max_number)")
        elif t is str:
            if len(node) > max_str:
                raise MessageError(json_path(path), f"a string of {len(node)} characters ({quote(node, 40)}) "
                                                    f"is longer than {max_str} ([limits] max_string_chars)")
        elif t is list:
            if len(node) > max_len:
                raise MessageError(json_path(path), f"an array of {len(node)} items is longer than any "
                                                    f"[limits] allows ({longest} = {max_len})")
            for i in range(len(node) - 1, -1, -1):
                v = node[i]
                tv = type(v)
                if tv is float or tv is int:  # the common case, without a stack entry
                    if not math.isfinite(v) or abs(v) > max_num:
                        stack.append((v, (*path, i)))
                elif tv is not bool and v is not None:
                    stack.append((v, (*path, i)))
        elif t is dict:
            for k, v in node.items():
                if len(k) > max_str:
                    raise MessageError(json_path(path), f"a key of {len(k)} characters ({quote(k, 40)}) is longer "
                                                        f"than {max_str} ([limits] max_string_chars)")
                stack.append((v, (*path, k)))
