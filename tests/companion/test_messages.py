from __future__ import annotations

import json

import pytest

from companion.wire.decode import check_geofence, decode, schema
from companion.wire.messages import KINDS, MessageError


def rejected(kind: str, payload: bytes | dict, max_bytes: int = 1 << 20) -> MessageError:
    raw = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
    with pytest.raises(MessageError) as info:
        decode(kind, raw, max_bytes=max_bytes, max_waypoints=100, max_obstacles=10)
    return info.value


def test_schemas_load_from_the_package() -> None:
    for kind in KINDS:
        doc = schema(kind)
        assert doc["title"] == kind
        assert doc["$schema"].startswith("https://json-schema.org/")


def test_valid_messages_pass() -> None:
    ok = {"id": "m", "frame": "enu", "waypoints": [[0, 0, 1], [1, 2, 3]], "durations": [2.0],
          "bounds": {"velocity": 2, "acceleration": [-2, 3], "jerk": [[-1, 1], [-2, 2], [-3, 3]]},
          "obstacles": [{"A": [[1, 0, 0]], "b": [1]}, {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]}]}
    assert decode("mission", json.dumps(ok).encode(), max_bytes=1 << 20)["id"] == "m"
    assert decode("command", b'{"command": "takeoff", "altitude": 3}', max_bytes=100)["altitude"] == 3
    assert "append" in decode("change", b'{"append": {"waypoints": [[1, 2, 3]]}}', max_bytes=1000)


@pytest.mark.parametrize(
    ("kind", "payload", "field", "words"),
    [
        ("mission", b"{", "", "malformed JSON"),
        ("mission", b"\xff\xfe", "", "not UTF-8"),
        ("mission", b'{"id": "a", "waypoints": [[0, 0, NaN]]}', "waypoints[0][2]", "non-finite"),
        ("mission", b'{"id": "a", "waypoints": [[0, 0, 1e999]]}', "waypoints[0][2]", "non-finite"),
        ("mission", {"id": "a", "waypoints": [[0, 0, 0], [1, 2]]}, "waypoints[1]", "too short"),
        ("mission", {"id": "a", "waypoints": [[0, 0, 0], [1, 2, "x"]]}, "waypoints[1][2]", "not of type"),
        ("mission", {"waypoints": [[0, 0, 0]]}, "", "'id' is a required property"),
        ("mission", {"id": "a", "waypoints": [[0, 0, 0]], "speed": 3}, "", "speed"),
        ("mission", {"id": "a", "waypoints": [[0, 0, 0], [1, 1, 1]], "durations": [1, 2]}, "durations", "expected 1"),
        ("mission", {"id": "a", "waypoints": [[0, 0, 0], [1, 1, 1]], "times": [1, 1]}, "times[1]", "increase"),
        ("mission", {"id": "a", "waypoints": [[0, 0, 0]], "bounds": {"velocity": -1}}, "bounds.velocity", "minimum"),
        ("mission", {"id": "a", "waypoints": [[0, 0, 0]] * 101}, "waypoints", "limit"),
        ("obstacles", {"add": [{"id": "o", "A": [[1, 0, 0]], "b": [1, 2]}]}, "add[0].b", "expected 1"),
        ("obstacles", {"add": [{"id": "o", "vertices": [[0, 0, 0]]}]}, "add[0].vertices", "too short"),
        ("obstacles", {"frame": "ecef", "clear": True}, "frame", "is not one of"),
        ("change", {"move_waypoint": {"index": -1, "position": [0, 0, 0]}}, "move_waypoint.index", "minimum"),
        ("change", {"teleport": {}}, "", "teleport"),
        ("change", {"append": {"waypoints": [[1, 2, 3]], "durations": [1, 2]}}, "append.durations", "expected 1"),
        ("command", {"command": "fly"}, "command", "is not one of"),
        ("command", {"command": "takeoff", "altitude": 0}, "altitude", "minimum"),
        ("command", [1, 2], "", "is not of type 'object'"),
    ],
)
def test_rejections_name_the_field(kind: str, payload: bytes | dict, field: str, words: str) -> None:
    err = rejected(kind, payload)
    assert err.field == field, err
    assert words in err.reason, err


def test_size_limit_is_checked_before_parsing() -> None:
    err = rejected("mission", b" " * 2000, max_bytes=1000)
    assert "2000 bytes exceeds the limit of 1000" in err.reason


def test_geofence_names_the_first_offender() -> None:
    check_geofence([[0, 0, -1]], [-1, -1, -2], [1, 1, 0], "waypoints")
    with pytest.raises(MessageError) as info:
        check_geofence([[0, 0, -1], [0, 0, -1], [5, 0, -1]], [-1, -1, -2], [1, 1, 0], "waypoints")
    assert info.value.field == "waypoints[2]"
    assert "geofence" in info.value.reason


def _decode(kind: str, obj: dict) -> dict:
    return decode(kind, json.dumps(obj).encode(), max_bytes=1 << 20, max_waypoints=100, max_obstacles=10)


def _box_planes() -> tuple[list[list[float]], list[float]]:
    eye = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    return eye + [[-x for x in row] for row in eye], [1.0, 2.0, 3.0, 1.0, 2.0, 3.0]


@pytest.mark.parametrize(("region", "field", "words"), [
    # the long, well-formed arrays skip the schema walk; a malformed one is walked whole,
    # so the schema still names the exact element at fault
    ({"A": "planes", "b": [1, 2, 3, 1, 2, True]}, "add[0].b[5]", "not of type 'number'"),
    ({"A": "planes-bad-row", "b": [1, 2, 3, 1, 2, 3]}, "add[0].A[4]", "too short"),
    ({"A": "planes-bad-value", "b": [1, 2, 3, 1, 2, 3]}, "add[0].A[3][1]", "not of type 'number'"),
    ({"A": "planes", "b": [1, 2, 3]}, "add[0].b", "expected 6"),
    ({"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [1, "x", 0]]},
     "add[0].vertices[5][1]", "not of type 'number'"),
    ({"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]]}, "add[0].vertices", "too short"),
])
def test_obstacle_arrays_are_checked_whole(region: dict, field: str, words: str) -> None:
    planes, _ = _box_planes()
    if region.get("A") == "planes":
        region = {**region, "A": planes}
    elif region.get("A") == "planes-bad-row":
        region = {**region, "A": [*planes[:4], [1.0, 0.0], planes[5]]}
    elif region.get("A") == "planes-bad-value":
        region = {**region, "A": [*planes[:3], [0.0, None, 1.0], *planes[4:]]}
    with pytest.raises(MessageError) as exc:
        _decode("obstacles", {"add": [{"id": "o", **region}]})
    assert exc.value.field == field and words in exc.value.reason, (exc.value.field, exc.value.reason)


def test_long_obstacles_pass_whole() -> None:
    planes, b = _box_planes()
    cube = [[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)]
    msg = {"frame": "enu", "remove": ["old"],
           "add": [{"id": "p", "A": planes, "b": b}, {"id": "v", "vertices": cube}]}
    assert _decode("obstacles", msg) == msg


def test_the_protocol_doc_lists_exactly_the_key_space() -> None:
    """Issue 22.3: one source for the Zenoh keys (companion/wire/keys.py); the doc's table names
    each with its direction, and no other."""
    import re
    from pathlib import Path

    from companion.wire.keys import ALIVE, INBOUND, OUTBOUND, QUERYABLE

    doc = (Path(__file__).resolve().parents[2] / "docs" / "protocol.md").read_text()
    section = doc[doc.index("The key names have one source"):doc.index("Only the exact key of this vehicle")]
    table = dict(re.findall(r"^\| `(\w+)` \| ([^|]+) \|", section, re.MULTILINE))
    assert set(table) == {*INBOUND, *OUTBOUND, *QUERYABLE, ALIVE}, table
    assert all(table[k].startswith("in") for k in INBOUND)
    assert all(table[k].startswith("out") for k in OUTBOUND)
    assert all("query" in table[k] for k in QUERYABLE) and "liveliness" in table[ALIVE]
