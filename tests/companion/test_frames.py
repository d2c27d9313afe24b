from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from companion.wire.frames import (
    P,
    change_to_ned,
    obstacles_to_ned,
    scenario_to_ned,
    swap_box,
    swap_halfspaces,
    swap_points,
)

finite = st.floats(-1e3, 1e3, allow_nan=False)
vec = st.lists(finite, min_size=3, max_size=3)


@given(st.lists(vec, min_size=1, max_size=8))
def test_points_round_trip(points: list[list[float]]) -> None:
    p = np.asarray(points)
    assert np.allclose(swap_points(swap_points(p)), p)


def test_enu_to_ned_axes() -> None:
    assert swap_points([1.0, 2.0, 3.0]).tolist() == [2.0, 1.0, -3.0]
    assert np.allclose(P @ P, np.eye(3))


@given(st.lists(vec, min_size=1, max_size=5), st.lists(finite, min_size=5, max_size=5), st.lists(vec, min_size=5, max_size=5))
def test_halfspaces_keep_membership(rows: list[list[float]], b: list[float], pts: list[list[float]]) -> None:
    A = np.asarray(rows)
    bb = np.asarray(b[: len(rows)])
    x_enu = np.asarray(pts)
    inside_enu = np.all(x_enu @ A.T <= bb, axis=1)
    inside_ned = np.all(swap_points(x_enu) @ swap_halfspaces(A).T <= bb, axis=1)
    assert (inside_enu == inside_ned).all() or np.any(np.isclose(x_enu @ A.T, bb))


def test_box_swaps_and_flips_z() -> None:
    lo, hi = swap_box([0, 1, 2], [3, 4, 5])
    assert lo.tolist() == [1, 0, -5] and hi.tolist() == [4, 3, -2]


def test_scenario_to_ned_round_trip_and_bounds() -> None:
    enu = {"id": "m", "frame": "enu", "waypoints": [[1, 2, 3], [4, 5, 6]],
           "bounds": {"velocity": 2, "acceleration": [-1, 2], "jerk": [[-1, 1], [-2, 2], [-3, 4]]},
           "obstacles": [{"A": [[1, 0, 0]], "b": [1]}, {"vertices": [[0, 0, 1], [1, 0, 1], [0, 1, 1], [0, 0, 2]]}],
           "map": {"min": [-1, -2, 0], "max": [1, 2, 10]}, "initial": {"velocity": [1, 0, 0.5]}}
    ned = scenario_to_ned(enu)
    assert ned["frame"] == "ned"
    assert ned["waypoints"] == [[2, 1, -3], [5, 4, -6]]
    assert ned["bounds"]["velocity"] == 2 and ned["bounds"]["acceleration"] == [-1, 2]
    assert ned["bounds"]["jerk"] == [[-2, 2], [-1, 1], [-4, 3]]
    assert ned["obstacles"][0]["A"] == [[0, 1, 0]]
    assert ned["map"] == {"min": [-2, -1, -10], "max": [2, 1, 0]}
    assert ned["initial"]["velocity"] == [0, 1, -0.5]
    assert scenario_to_ned(ned) == ned  # already NED: unchanged


def test_obstacles_and_change_to_ned() -> None:
    ob = obstacles_to_ned({"frame": "enu", "add": [{"id": "a", "vertices": [[1, 2, 3]] * 4}], "remove": ["b"]})
    assert ob["add"][0]["vertices"][0] == [2, 1, -3] and ob["remove"] == ["b"]
    ch = change_to_ned({"frame": "enu", "move_waypoint": {"index": 2, "position": [1, 2, 3]}})
    assert ch["move_waypoint"] == {"index": 2, "position": [2, 1, -3]}
    ap = change_to_ned({"frame": "enu", "append": {"waypoints": [[1, 2, 3]], "durations": [2]}})
    assert ap["append"] == {"waypoints": [[2, 1, -3]], "durations": [2]}
