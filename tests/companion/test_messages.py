from __future__ import annotations

import json

import pytest

from companion.messages import KINDS, MessageError, check_geofence, decode, schema


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
