"""A replan's change counts the user's waypoints even when the fastest allocation put knots
on long legs: the planner CLI writes the map ("waypoint_index"), `replan` maps through it
(`planner_core.indices`), writes the new one and names user indices in its messages."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from planner_core import ChangeError, SetDuration, WaypointMap, parse_change, to_planned
from planner_core.formats.cli import main
from planner_core.formats.io import trajectory_from_dict, waypoint_index_from_dict
from planner_core.problem import Trajectory

WAYPOINTS = np.array([[0.0, 0.0, 1.0], [20.0, 0.0, 1.0], [20.0, 2.0, 1.0], [0.0, 2.0, 1.0]])
BOX = {"A": [[1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1]], "b": [21, 3, 2, 1, 1, 0]}
# no durations: the fastest allocation, which splits the two 20 m legs with knots
SCENARIO = {"waypoints": WAYPOINTS.tolist(), "bounds": {"velocity": 3, "acceleration": 3, "jerk": 10, "snap": 50},
            "corridors": [BOX] * 3}


@pytest.fixture(scope="module")
def planned(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict[str, Any]]:
    d = tmp_path_factory.mktemp("knots")
    scenario, traj = d / "scenario.json", d / "traj.json"
    scenario.write_text(json.dumps(SCENARIO))
    assert main(["plan", str(scenario), "-o", str(traj)]) == 0
    raw = json.loads(traj.read_text())
    index = raw["waypoint_index"]
    assert len(index) == 4 and index[-1] == len(raw["segments"]) and np.all(np.diff(index) >= 1)
    assert np.diff(index)[0] > 1 and np.diff(index)[2] > 1  # both long legs hold knots
    return scenario, traj, raw


def _replan(tmp: Path, scenario: Path, traj: Path, change: dict[str, Any]) -> tuple[int, dict[str, Any] | None]:
    (tmp / "change.json").write_text(json.dumps(change))
    out = tmp / "out.json"
    out.unlink(missing_ok=True)
    rc = main(["replan", str(scenario), str(traj), str(tmp / "change.json"), "-o", str(out)])
    return rc, json.loads(out.read_text()) if out.exists() else None


def _on_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    ab = b - a
    return bool(np.linalg.norm(np.cross(ab, p - a)) < 1e-9 and -1e-9 <= (p - a) @ ab <= ab @ ab + 1e-9)


def _user_waypoints(raw: dict[str, Any]) -> tuple[Trajectory, np.ndarray, np.ndarray]:
    traj = trajectory_from_dict(raw)
    index = waypoint_index_from_dict(raw)
    assert index is not None
    return traj, index, traj.waypoints[index]


def test_move_counts_user_waypoints_and_knots_follow(planned: tuple[Path, Path, dict[str, Any]],
                                                     tmp_path: Path) -> None:
    scenario, traj_path, raw = planned
    old, index, _ = _user_waypoints(raw)
    target = np.array([18.0, 2.5, 1.0])
    rc, new_raw = _replan(tmp_path, scenario, traj_path, {"move": {"index": 2, "position": target.tolist()}})
    assert rc == 0 and new_raw is not None
    new, new_index, users = _user_waypoints(new_raw)
    assert new_index.tolist() == index.tolist()
    assert np.allclose(new.evaluate(new.times[index[2]]), target, atol=1e-9)
    assert np.allclose(users[[0, 1, 3]], WAYPOINTS[[0, 1, 3]], atol=1e-9)
    for k in range(index[2] + 1, index[3]):  # the moved leg's knots stay on it, in order
        assert _on_segment(new.waypoints[k], target, WAYPOINTS[3])
    assert np.array_equal(new.control_points[0], old.control_points[0])  # far from the change: kept
    assert new_raw["stats"]["resolved_jets"] and set(new_raw["stats"]["resolved_jets"]) <= {0, 1, 2, 3}
    # the written map carries on: a chained replan still counts user waypoints
    (tmp_path / "moved.json").write_text(json.dumps(new_raw))
    rc, again = _replan(tmp_path, scenario, tmp_path / "moved.json", {"move": {"index": 1, "position": [19, 0.5, 1]}})
    assert rc == 0 and again is not None
    _, _, users = _user_waypoints(again)
    assert np.allclose(users, [WAYPOINTS[0], [19, 0.5, 1], target, WAYPOINTS[3]], atol=1e-9)


def test_duration_of_a_knotted_segment_is_its_total(planned: tuple[Path, Path, dict[str, Any]],
                                                    tmp_path: Path) -> None:
    scenario, traj_path, raw = planned
    old, index, _ = _user_waypoints(raw)
    want = 1.3 * float(old.times[index[1]] - old.times[index[0]])
    rc, new_raw = _replan(tmp_path, scenario, traj_path, {"duration": {"segment": 0, "duration": want}})
    assert rc == 0 and new_raw is not None
    new, new_index, users = _user_waypoints(new_raw)
    assert new_index.tolist() == index.tolist() and np.allclose(users, WAYPOINTS, atol=1e-9)
    assert new.times[index[1]] - new.times[index[0]] == pytest.approx(want, rel=1e-12)
    ratio = np.diff(new.times)[: index[1]] / np.diff(old.times)[: index[1]]
    assert np.allclose(ratio, 1.3, rtol=1e-9)  # spread over the pieces in proportion
    assert np.allclose(np.diff(new.times)[index[1]:], np.diff(old.times)[index[1]:], rtol=1e-12)


def test_remove_merges_the_legs_and_their_knots(planned: tuple[Path, Path, dict[str, Any]], tmp_path: Path) -> None:
    scenario, traj_path, raw = planned
    old, index, _ = _user_waypoints(raw)
    rc, new_raw = _replan(tmp_path, scenario, traj_path, {"remove_waypoint": {"index": 1}})
    assert rc == 0 and new_raw is not None
    new, new_index, users = _user_waypoints(new_raw)
    assert new.n_segments == old.n_segments - 1  # one user waypoint gone, every knot kept
    assert new_index.tolist() == [0, index[2] - 1, index[3] - 1]
    assert np.allclose(users, WAYPOINTS[[0, 2, 3]], atol=1e-9)
    a, b = WAYPOINTS[0], WAYPOINTS[2]
    t0, t1 = new.times[0], new.times[new_index[1]]
    for k in range(1, new_index[1]):  # on the merged straight leg, at their fraction of its time
        assert _on_segment(new.waypoints[k], a, b)
        assert np.allclose(new.waypoints[k], a + (b - a) * (new.times[k] - t0) / (t1 - t0), atol=1e-9)


def test_insert_goes_between_the_knots(planned: tuple[Path, Path, dict[str, Any]], tmp_path: Path) -> None:
    scenario, traj_path, raw = planned
    _, index, _ = _user_waypoints(raw)
    pos = np.array([10.0, 2.5, 1.0])
    rc, new_raw = _replan(tmp_path, scenario, traj_path, {"insert": {"index": 3, "position": pos.tolist()}})
    assert rc == 0 and new_raw is not None
    new, new_index, users = _user_waypoints(new_raw)
    assert new_index.size == 5 and new.n_segments == index[-1] + 1
    assert np.allclose(users, [WAYPOINTS[0], WAYPOINTS[1], WAYPOINTS[2], pos, WAYPOINTS[3]], atol=1e-9)
    for k in range(new_index[2] + 1, new_index[3]):
        assert _on_segment(new.waypoints[k], WAYPOINTS[2], pos)
    for k in range(new_index[3] + 1, new_index[4]):
        assert _on_segment(new.waypoints[k], pos, WAYPOINTS[3])


@pytest.mark.parametrize(("change", "words"), [
    ({"move": {"index": 4, "position": [1, 1, 1]}}, ["move.index", "waypoint 4 out of range 0..3", "4 waypoints"]),
    ({"duration": {"segment": 3, "duration": 5}}, ["duration.segment", "segment 3 out of range 0..2", "4 waypoints"]),
    ({"remove": {"index": 3}}, ["remove.index", "waypoint 3 out of range 1..2", "4 waypoints"]),
])
def test_out_of_range_names_the_user_index(planned: tuple[Path, Path, dict[str, Any]], tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str], change: dict[str, Any],
                                           words: list[str]) -> None:
    scenario, traj_path, _ = planned
    rc, out = _replan(tmp_path, scenario, traj_path, change)
    err = capsys.readouterr().err
    assert rc == 2 and out is None
    for w in words:
        assert w in err
    assert "knot" not in err


def test_a_file_without_the_map_counts_every_boundary(planned: tuple[Path, Path, dict[str, Any]],
                                                      tmp_path: Path) -> None:
    scenario, _, raw = planned
    old_style = {k: v for k, v in raw.items() if k != "waypoint_index"}
    (tmp_path / "old.json").write_text(json.dumps(old_style))
    old = trajectory_from_dict(old_style)
    target = old.waypoints[2] + np.array([0.0, 0.5, 0.0])  # planned waypoint 2: a knot on the first leg
    rc, new_raw = _replan(tmp_path, scenario, tmp_path / "old.json", {"move": {"index": 2, "position": target.tolist()}})
    assert rc == 0 and new_raw is not None
    new = trajectory_from_dict(new_raw)
    assert np.allclose(new.waypoints[2], target, atol=1e-9)
    others = np.arange(old.n_segments + 1) != 2
    assert np.allclose(new.waypoints[others], old.waypoints[others], atol=1e-9)
    assert new_raw["waypoint_index"] == list(range(old.n_segments + 1))
    assert 2 in new_raw["stats"]["resolved_jets"] and "planned" not in new_raw["stats"]


def test_from_time_keeps_the_flown_part_of_a_duration(planned: tuple[Path, Path, dict[str, Any]]) -> None:
    _, _, raw = planned
    traj, index, _ = _user_waypoints(raw)
    wm = WaypointMap(index, traj.n_segments + 1)
    t_from = 0.5 * float(traj.times[1] + traj.times[2])  # inside the second piece of segment 0
    total = float(traj.times[index[1]] - traj.times[0])
    mapped = to_planned(parse_change({"from_time": t_from, "duration": {"segment": 0, "duration": total + 2.0}}),
                        wm, traj.waypoints, traj.times)
    edits = [e for e in mapped.change.edits if isinstance(e, SetDuration)]
    assert len(edits) == len(mapped.change.edits)
    assert [e.segment for e in edits] == list(range(2, index[1]))  # flown and being flown: untouched
    new = np.diff(traj.times)
    for e in edits:
        new[e.segment] = e.duration
    assert float(np.sum(new[: index[1]])) == pytest.approx(total + 2.0, rel=1e-12)
    with pytest.raises(ChangeError, match=r"duration\.duration: segment 0: .* flown or being flown"):
        to_planned(parse_change({"from_time": t_from, "duration": {"segment": 0, "duration": float(traj.times[2])}}),
                   wm, traj.waypoints, traj.times)
    with pytest.raises(ChangeError, match=r"move\.index: waypoint 0 is at or before from_time"):
        to_planned(parse_change({"from_time": t_from, "move": {"index": 0, "position": [0, 0, 1]}}),
                   wm, traj.waypoints, traj.times)


def test_from_time_split_is_a_knot_in_the_new_map(planned: tuple[Path, Path, dict[str, Any]], tmp_path: Path) -> None:
    scenario, traj_path, raw = planned
    old, index, _ = _user_waypoints(raw)
    t_from = 0.5 * float(old.times[1] + old.times[2])
    target = [19.0, 0.5, 1.0]
    rc, new_raw = _replan(tmp_path, scenario, traj_path,
                          {"from_time": t_from, "move": {"index": 1, "position": target}})
    assert rc == 0 and new_raw is not None
    new, new_index, users = _user_waypoints(new_raw)
    assert new.n_segments == old.n_segments + 1 and new_index.tolist() == [0, *(index[1:] + 1)]
    assert np.allclose(users, [WAYPOINTS[0], target, WAYPOINTS[2], WAYPOINTS[3]], atol=1e-9)
    assert np.allclose(new.evaluate(t_from), old.evaluate(t_from), atol=1e-9)  # the flown part is kept
    for k in range(4, new_index[1]):  # knots after the piece being flown follow the moved leg
        assert _on_segment(new.waypoints[k], WAYPOINTS[0], np.array(target))
