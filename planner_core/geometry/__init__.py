"""Safe corridors: one convex polytope per segment, built from obstacle polytopes.

(Was `planner_core/corridors.py`; split by concern, same code.)

A corridor bounds the vehicle *centre* (the planner keeps every control point
of segment j inside corridor j). With vehicle radius r, corridor j = {x : A x <= b}
(unit rows) satisfies, by construction:

- Containment: the straight segment [W_j, W_{j+1}] is inside, at distance >= r
  from every obstacle plane (so the curve has room to bend) and inside the map
  planes (the vehicle centre stays in the map box shrunk by r) and the faces of
  its analysis box (below), which are farther.
- Exclusion (checkable certificate): for every obstacle O there is one corridor
  plane with all vertices of O at signed distance >= r beyond it, so the ball of
  radius r around any corridor point misses O.
- Room: an obstacle's plane has the maximum-margin normal between the segment
  and the obstacle (the hard-margin SVM's normal, which for disjoint convex sets
  is the direction of their closest pair: found in closed form over feature
  pairs, many segments per obstacle at once, see `separations`) and is pushed
  to the obstacle side as far as safety allows: offset = min_v a.v - r. The
  segment then keeps clearance gap - r >= r from it, where gap = min_v a.v -
  max_p a.p is recomputed from the normal (safety never rests on the solver).
- Blocked: a segment is flyable only if the segment inflated by r and the
  obstacle inflated by r are disjoint (gap >= 2r); otherwise CorridorError.
  Obstacles already kept r beyond the shrunk map box count as outside the map.
- Analysis box (the broad phase, the plane choice of this builder): each
  segment's corridor starts as its bounding box padded by `influence` (default
  length + 3 m), clipped to the map box shrunk by r. An obstacle that a face of
  that box already keeps r away (its bounding box lies beyond the face) needs no
  plane: it is never looked at again (`broadphase`: a sorted sweep finds the
  others, the candidates). So a corridor costs what its neighbourhood holds, not
  what the map holds; a far obstacle is excluded by a box face instead of by a
  plane of its own, and never changes the region.
- Economy: the planes of all (segment, candidate) pairs are computed in one
  batch; nearest first, a candidate keeps its plane only when no nearer
  candidate's plane already certifies it (dropping a certified obstacle's plane
  only gives room). Then, for all corridors with as many planes at once
  (`facets`: plane-triple vertices in closed form), planes that are not facets
  are dropped, unless a candidate's plane is the certificate a candidate would
  lose, or a box face has obstacles beyond it (counted with a sorted sweep;
  removing such planes would not change the region, but the certificate is what
  makes exclusion checkable with one matrix product).
- Pop-ups (`update_corridors`): only corridors that no plane (box faces
  included) already certifies against the new obstacle are touched.

Modules, by concern:
- `polytopes`: vertex enumeration (H -> V, cached), convex hulls (V -> H), queries;
- `separating`: the maximum-margin plane between a segment and an obstacle, one pair or
  many pairs at once;
- `obstacles`: the obstacle set as the builders read it, the map box, analysis boxes;
- `pruning`: dropping planes that do not shape a corridor (keeping certificates);
- `building`: `build_corridors`; `update`: `update_corridors` (pop-ups);
- `common`: `CorridorError`, `CERT_TOL`.
"""

from planner_core.geometry.building import (
    DEFAULT_INFLUENCE_MARGIN,
    Separation,
    analysis_boxes,
    build_corridors,
)
from planner_core.geometry.common import CERT_TOL, BoolArray, CorridorError, IntArray
from planner_core.geometry.polytopes import (
    SMALL_HULL_POINTS,
    axis_box_of,
    clear_vertex_cache,
    corridor_contains_segment,
    exclusion_margin,
    normalised,
    polytope_from_box,
    polytope_from_vertices,
    polytope_vertices,
    segment_clearance,
)
from planner_core.geometry.separating import max_margin_normal, separation, separations
from planner_core.geometry.update import update_corridors

__all__ = [
    "CERT_TOL",
    "DEFAULT_INFLUENCE_MARGIN",
    "SMALL_HULL_POINTS",
    "BoolArray",
    "CorridorError",
    "IntArray",
    "Separation",
    "analysis_boxes",
    "axis_box_of",
    "build_corridors",
    "clear_vertex_cache",
    "corridor_contains_segment",
    "exclusion_margin",
    "max_margin_normal",
    "normalised",
    "polytope_from_box",
    "polytope_from_vertices",
    "polytope_vertices",
    "segment_clearance",
    "separation",
    "separations",
    "update_corridors",
]
