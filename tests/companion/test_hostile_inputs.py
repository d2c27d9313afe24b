"""Issue 21.3 and 21.4: duplicate JSON keys are refused at every level, naming the key path;
degenerate durations and planner failures are answered in the sender's terms (a field and a
reason), and an exception from the planner is a refusal that says so, never an `error`."""

from __future__ import annotations

import json
import logging
from typing import Any

import numpy as np
import pytest

from companion import mission as mission_mod
from companion.config import Config
from companion.edits import Refused, resolve_planned
from companion.mission import start_mission, trim
from companion.obstacles import Known
from companion.wire.messages import InternalError, MessageError, MissionSpec, read, warm_validators
from planner_core import rest_jet

CFG = Config()
CUBE = '[[0,0,0],[1,0,0],[0,1,0],[0,0,1],[1,1,1],[1,1,0],[1,0,1],[0,1,1]]'


def refused(kind: str, text: str) -> MessageError:
    out = read(kind, text.encode(), CFG)
    assert isinstance(out, MessageError) and not isinstance(out, InternalError), out
    return out


@pytest.mark.parametrize(("kind", "text", "field"), [
    # the case: the obstacle silently dropped by "last wins"
    ("obstacles", '{"add": [{"id": "a", "vertices": ' + CUBE + '}], "add": []}', "add"),
    ("obstacles", '{"add": [{"id": "a", "id": "b", "vertices": ' + CUBE + '}]}', "add[0].id"),
    ("obstacles", '{"add": [{"id": "a", "vertices": ' + CUBE + '}, {"id": "b", "A": [[1,0,0]], "b": [1], "b": [2]}]}',
     "add[1].b"),
    ("mission", '{"id": "m", "waypoints": [[1,0,-1]], "waypoints": [[2,0,-1]]}', "waypoints"),
    ("mission", '{"id": "m", "waypoints": [[1,0,-1]], "bounds": {"velocity": 1, "velocity": 9}}', "bounds.velocity"),
    ("mission", '{"id": "m", "waypoints": [[1,0,-1]], "map": {"min": [0,0,-5], "max": [9,9,0], "min": [1,1,1]}}',
     "map.min"),
    ("change", '{"move_waypoint": {"index": 1, "position": [1,0,-1], "index": 2}}', "move_waypoint.index"),
    ("command", '{"command": "arm", "command": "disarm"}', "command"),
])
def test_duplicate_keys_are_refused_naming_the_key_path(kind: str, text: str, field: str) -> None:
    err = refused(kind, text)
    assert err.field == field and "more than once" in err.reason, err


def test_a_key_repeated_in_different_objects_is_not_a_duplicate() -> None:
    warm_validators()  # the first hull imports scipy: not within the decode deadline on a busy machine
    ok = read("obstacles", ('{"add": [{"id": "a", "vertices": ' + CUBE + '}, {"id": "b", "vertices": ' + CUBE
                            + '}]}').encode(), CFG)
    assert not isinstance(ok, MessageError), ok


WPS = [[0, 0, -1.5], [3, 0, -1.5], [3, 3, -1.5]]


@pytest.mark.parametrize(("kind", "obj", "field", "words"), [
    ("mission", {"id": "m", "waypoints": WPS, "durations": [1e-9, 2]}, "durations[0]", "min_segment_duration"),
    ("mission", {"id": "m", "waypoints": WPS, "durations": [2, 9e4]}, "durations[1]", "max_segment_duration"),
    ("mission", {"id": "m", "waypoints": WPS, "durations": [1e-9, 9e4]}, "durations[0]", "min_segment_duration"),
    ("mission", {"id": "m", "waypoints": WPS, "times": [0, 2, 2 + 1e-9]}, "times[2]", "min_segment_duration"),
    # 3 m within 3 m/s: no curve does it in less than 1 s (a proven floor, not a guess)
    ("mission", {"id": "m", "waypoints": WPS, "durations": [2, 0.5]}, "durations[1]", "less than 1 s"),
    ("change", {"duration": {"index": 2, "value": 1e-9}}, "duration.value", "min_segment_duration"),
    ("change", {"duration": {"index": 2, "value": 9e4}}, "duration.value", "max_segment_duration"),
    ("change", {"append": {"waypoints": [[1, 1, -1]], "durations": [1e-9]}}, "append.durations[0]",
     "min_segment_duration"),
])
def test_degenerate_durations_are_refused_naming_the_field(kind: str, obj: dict[str, Any], field: str,
                                                           words: str) -> None:
    err = refused(kind, json.dumps(obj))
    assert err.field == field and words in err.reason, err


def _spec(obj: dict[str, Any]) -> MissionSpec:
    spec = read("mission", json.dumps(obj).encode(), CFG)
    assert isinstance(spec, MissionSpec), spec
    return spec


def test_a_planner_failure_is_named_by_the_senders_field_not_the_planners_segment() -> None:
    # in flight (moving at 1 m/s, accelerating at 4 m/s^2: beyond the mission's 3, so no lead
    # knot helps) with a leg of 3000 s: the planner's "bounds of segment 0 fixed by the initial
    # state" said as the leg and the duration the sender gave
    jet = rest_jet(np.array([0.0, 0.0, -1.5]))
    jet[1], jet[2] = [1.0, 0.5, 0.0], [4.0, 0.0, 0.0]
    spec = _spec({"id": "m", "waypoints": [[0.05, 0, -1.5], [3, 0, -1.5], [3, 3, -1.5]], "durations": [3000, 3]})
    out = start_mission(spec, jet, 0.0, Known(), CFG)
    assert not out.ok and out.field == "durations[0]", out
    assert "segment" not in out.message and "waypoint 0 to waypoint 1" in out.message, out.message


def test_start_far_from_the_first_waypoint_names_start() -> None:
    spec = _spec({"id": "m", "waypoints": [[5, 5, -1.5], [3, 0, -1.5]], "start": "first_waypoint"})
    out = start_mission(spec, rest_jet(np.array([0.0, 0.0, -1.5])), 0.0, Known(), CFG)
    assert not out.ok and out.field == "start" and "7.07 m from waypoint 0" in out.message


def test_a_duration_change_too_short_for_its_leg_is_refused_before_planning() -> None:
    spec = _spec({"id": "m", "waypoints": [[3, 0, -1.5], [6, 0, -1.5], [6, 6, -1.5]], "durations": [2, 3]})
    route = start_mission(spec, rest_jet(np.array([0.0, 0.0, -1.5])), 0.0, Known(), CFG).route
    assert route is not None
    change = read("change", b'{"duration": {"index": 1, "value": 0.1}}', CFG)
    out = resolve_planned(trim(route, 0.2), change, 0.5, False)  # type: ignore[arg-type]
    assert isinstance(out, Refused) and out.field == "duration.value" and "less than 2 s" in out.reason, out


def test_an_exception_from_the_planner_is_a_refusal_that_says_so(monkeypatch: pytest.MonkeyPatch) -> None:
    """The issue's LinAlgError('Singular matrix') in the replan handler: whatever planner_core
    raises comes back as a refusal (the sender answered), and the traceback is logged."""
    def singular(*_: Any, **__: Any) -> Any:
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(mission_mod, "plan_with_detours", singular)
    spec = _spec({"id": "m", "waypoints": WPS})
    out = start_mission(spec, rest_jet(np.array([0.0, 0.0, -1.5])), 0.0, Known(), CFG)
    assert not out.ok and "LinAlgError: Singular matrix" in out.message and "bug" in out.message
    assert "Traceback" in out.stats["internal_error"]

    from types import SimpleNamespace

    from companion.mission_start import MissionStart
    from companion.split_swap import logged

    rejected: list[tuple[str, str, str]] = []
    nav: Any = SimpleNamespace(report=SimpleNamespace(reject=lambda k, f, r, **_: rejected.append((k, f, r))),
                               clipped_note=lambda _spec: "")  # no autopilot limits in this fake
    records: list[logging.LogRecord] = []
    handler = logging.Handler(logging.ERROR)
    handler.emit = records.append  # type: ignore[method-assign]
    logger = logging.getLogger("companion")
    logger.addHandler(handler)
    try:
        MissionStart.reject_outcome(nav, spec, logged(out))
    finally:
        logger.removeHandler(handler)
    assert rejected and rejected[0][0] == "mission" and "Singular matrix" in rejected[0][2]
    assert any("Traceback" in r.getMessage() for r in records)
