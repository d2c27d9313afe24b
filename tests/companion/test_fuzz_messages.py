"""Fuzzing the decoder: generated and mutated payloads for every inbound key against `read`.

Pure and fast (no Zenoh, no planning): thousands of cases. Every case must come back as a
typed message or a `MessageError` with a bounded field and reason; never an exception, never
an `InternalError` (the last-resort guard is for bugs, and a fuzz case that reaches it is one).
The counts are printed at the end (`pytest -s`) and asserted to be in the thousands.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.config import Config
from companion.wire.errors import MAX_QUOTE, MAX_REASON
from companion.wire.messages import (
    KINDS,
    Change,
    Command,
    InternalError,
    MessageError,
    MissionSpec,
    ObstacleUpdate,
    Oversized,
    read,
)

CFG = Config()
COUNTS: Counter[str] = Counter()
SLOWEST: list[float] = [0.0]
FUZZ = settings(max_examples=500, deadline=None, database=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def check(kind: str, payload: bytes | Oversized) -> None:
    t0 = time.perf_counter()
    result = read(kind, payload, CFG)  # must not raise
    SLOWEST[0] = max(SLOWEST[0], time.perf_counter() - t0)
    COUNTS["cases"] += 1
    assert not isinstance(result, InternalError), (kind, payload[:300], result)
    if isinstance(result, MessageError):
        COUNTS["rejected"] += 1
        assert result.reason, (kind, payload[:300])
        assert len(result.reason) <= MAX_REASON and len(result.field) <= MAX_QUOTE
    else:
        COUNTS["accepted"] += 1
        want = {"mission": MissionSpec, "obstacles": ObstacleUpdate, "change": Change, "command": Command}[kind]
        assert isinstance(result, want)


# -- values: sane ones, and hostile ones ---------------------------------------------------------

coord = st.floats(-30, 30, allow_nan=False)
vec3 = st.lists(coord, min_size=3, max_size=3)
HOSTILE_NUMBERS = [-1, 0, 1.5, -1e300, 1e300, 10**400, 2**63, -(2**64), 1e-320, True, None]
hostile_leaf = st.one_of(
    st.sampled_from(HOSTILE_NUMBERS),
    st.integers(), st.floats(allow_nan=False, allow_infinity=False),
    st.text(max_size=40), st.sampled_from(["", "x" * 5000, "\u0000", "\ud7ff" * 3, "arm", "enu"]),
)
hostile = st.recursive(hostile_leaf, lambda kids: st.one_of(
    st.lists(kids, max_size=6), st.dictionaries(st.text(max_size=8), kids, max_size=4)), max_leaves=20)


def box(lo: list[float], size: list[float]) -> dict[str, Any]:
    hi = [a + abs(s) for a, s in zip(lo, size, strict=True)]
    return {"A": [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
            "b": [hi[0], -lo[0], hi[1], -lo[1], hi[2], -lo[2]]}


region = st.one_of(
    st.builds(box, vec3, vec3),
    st.builds(lambda pts: {"vertices": pts}, st.lists(vec3, min_size=0, max_size=12)),
    st.builds(lambda a, b: {"A": a, "b": b}, st.lists(vec3, max_size=8), st.lists(coord, max_size=8)),
)
obstacle = st.builds(lambda i, r: {"id": i, **r}, st.text(min_size=1, max_size=6), region)
bound = st.one_of(st.floats(0.1, 20), st.tuples(st.floats(-20, -0.1), st.floats(0.1, 20)).map(list))
FIELDS: dict[str, dict[str, Any]] = {
    "mission": {
        "id": st.text(min_size=1, max_size=8), "frame": st.sampled_from(["enu", "ned", "ecef"]),
        "waypoints": st.lists(vec3, min_size=1, max_size=8), "durations": st.lists(st.floats(0.1, 10), max_size=8),
        "times": st.lists(st.floats(0, 50), max_size=8),
        "bounds": st.fixed_dictionaries({}, optional={"velocity": bound, "acceleration": bound, "jerk": bound}),
        "obstacles": st.lists(obstacle, max_size=3), "vehicle_radius": st.floats(0, 2),
        "map": st.fixed_dictionaries({"min": vec3, "max": vec3}), "start": st.sampled_from(["current", "first_waypoint"]),
        "autostart": st.booleans(), "initial": st.fixed_dictionaries({}, optional={"velocity": vec3}),
    },
    "obstacles": {
        "add": st.lists(obstacle, max_size=3), "remove": st.lists(st.text(max_size=6), max_size=3),
        "clear": st.booleans(), "frame": st.sampled_from(["enu", "ned"]),
    },
    "change": {
        "move_waypoint": st.fixed_dictionaries({"index": st.integers(-1, 10), "position": vec3}),
        "insert_waypoint": st.fixed_dictionaries({"index": st.integers(0, 10), "position": vec3}),
        "remove_waypoint": st.fixed_dictionaries({"index": st.integers(0, 10)}),
        "duration": st.fixed_dictionaries({"index": st.integers(0, 10), "value": st.floats(-1, 10)}),
        "append": st.fixed_dictionaries({"waypoints": st.lists(vec3, min_size=1, max_size=4)},
                                        optional={"durations": st.lists(st.floats(0.1, 5), max_size=4)}),
        "frame": st.sampled_from(["enu", "ned"]),
    },
    "command": {
        "command": st.sampled_from(["arm", "takeoff", "start", "hold", "resume", "land", "abort", "disarm", "fly"]),
        "altitude": st.floats(-10, 600),
    },
}


@st.composite
def message(draw: Any, kind: str) -> dict[str, Any]:
    """Some of the kind's fields, each sane or (sometimes) hostile, and now and then a stray key."""
    fields = FIELDS[kind]
    names = draw(st.lists(st.sampled_from(sorted(fields)), unique=True, max_size=len(fields)))
    if kind == "command" and "command" not in names:
        names.append("command")
    out: dict[str, Any] = {}
    for name in names:
        out[name] = draw(st.one_of(fields[name], hostile) if draw(st.integers(0, 5)) == 0 else fields[name])
    if draw(st.integers(0, 9)) == 0:
        out[draw(st.text(max_size=10))] = draw(hostile)
    return out


def mutate(text: str, how: int, at: int) -> bytes:
    """A textual mutation of a JSON document."""
    at = at % (len(text) + 1)
    if how == 0:
        return text[:at].encode()  # cut
    if how == 1:
        return (text[:at] + "9" * 5000 + text[at:]).encode()  # a huge literal
    if how == 2:
        return ("[" * 100_000 + text).encode()  # deep nesting
    if how == 3:
        return (text[:at] + "\xff\xfe" + text[at:]).encode("latin-1", "replace")  # not UTF-8
    if how == 4:
        return text.replace("1", "1e999").encode()  # overflowing floats
    if how == 5:
        return text.replace("]", ", NaN]").encode()
    if how == 6:
        return ('{"a":' * 50 + "1" + "}" * 50).encode()
    return (text[:at] + '"' + "\\u0000" * 50 + text[at:]).encode()


@pytest.mark.parametrize("kind", KINDS)
@FUZZ
@given(data=st.data())
def test_generated_messages(kind: str, data: Any) -> None:
    check(kind, json.dumps(data.draw(message(kind))).encode())


@pytest.mark.parametrize("kind", KINDS)
@FUZZ
@given(data=st.data(), how=st.integers(0, 7), at=st.integers(0, 10**6))
def test_mutated_messages(kind: str, data: Any, how: int, at: int) -> None:
    check(kind, mutate(json.dumps(data.draw(message(kind))), how, at))


@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=250, deadline=None, database=None, derandomize=True)
@given(payload=st.one_of(st.binary(max_size=200), hostile.map(lambda v: json.dumps(v).encode())))
def test_raw_payloads(kind: str, payload: bytes) -> None:
    check(kind, payload)


@pytest.mark.parametrize("kind", KINDS)
def test_oversized_payload_is_refused_unread(kind: str) -> None:
    check(kind, Oversized(100 << 20))
    err = read(kind, Oversized(100 << 20), CFG)
    assert isinstance(err, MessageError) and "max_message_bytes" in err.reason


def test_zz_counts() -> None:
    """Runs last in this file: the totals, for the record."""
    print(f"\nfuzz (decoder): {COUNTS['cases']} cases, {COUNTS['rejected']} rejected, "
          f"{COUNTS['accepted']} accepted, 0 crashes; slowest read {SLOWEST[0] * 1000:.1f} ms")
    if COUNTS["cases"]:  # when the whole file ran
        assert COUNTS["cases"] >= 5000
        assert COUNTS["accepted"] >= 100 and COUNTS["rejected"] >= 1000
