"""Separation between two vehicles' committed trajectories, in continuous time (method.md, "the fleet").

Two trajectories A(t), B(t) (piecewise degree 9, each with its own knots) on one absolute clock.
Their *overlap* runs from the later start to the later end: a trajectory that has ended holds its
last point (that point stays reserved), before its start it is not defined (the caller hands in
trajectories that cover "now"). On the overlap both are split exactly (de Casteljau, a linear map
of each segment's control points) at the union of their knots; on each common interval both are
degree-9 Bézier curves of the same parameter u with control points a_0..a_9 and b_0..b_9. A unit
vector n and a scalar c with

    n . a_k <= c - s'/2   and   n . b_k >= c + s'/2   for every k

keep |A(t) - B(t)| >= s' on the whole interval (convex hull). `s' = s + (v_A + v_B) eps` pays
for a clock offset of at most eps between the vehicles (v: bound speeds). After the overlap both
hold their last points, which are control points of the last interval: its plane certifies the
hold for ever.

- `certify_separation(a, b, s, ...)` -> `SeparationCheck` carrying a `SeparationCertificate` (one
  plane per interval, subdividing an interval where its margin is short) or naming the first
  interval that could not be certified and by how much.
- `verify_separation(a, b, cert)`: what any receiver runs; status-coded, never raises on a bad
  certificate.
- `certify_many(a, others, s, ...)`: the same against many trajectories in one batch;
  `certify_all(traj, neighbours)`: against every neighbour the broad phase finds near.
- Planning against neighbours: `Neighbours` (the other committed trajectories and the rules),
  `neighbour_faces` / `with_neighbours` (per segment of ours, half-spaces n . x <= c on our control
  points: a corridor face, so every planner path takes them and the QP stays a QP),
  `planning_rows` (time-resolved rows per common piece, for the general jet solver:
  `jets.ProblemCache(extra_rows=...)`), `separation_rows` (the rows of an existing certificate's
  intervals on our control points). `planning.plan(..., neighbours=)` and
  `replan.ReplanOptions(neighbours=)` use them (docs/separation.md).
- Broad phase: `near_pairs` (space-time boxes, a sorted sweep): far neighbours cost nothing.

Where it lives: `planner_core.separation_pieces` (exact pieces, speed bounds, planes),
`planner_core.separation_batch` (one trajectory against many stacked ones: knots, locations, boxes),
`planner_core.separation_certificate` (the certificate: certify, verify) and
`planner_core.separation_planning` (neighbours, broad phase, faces, rows, `certify_all`). This
module still names everything it held before the split (recorded planner calls find their classes and
functions by this path).

Pure numpy (plus daqp for the small max-margin QPs); no I/O.
"""

from __future__ import annotations

from planner_core.separation_certificate import (
    MAX_DEPTH as MAX_DEPTH,
)
from planner_core.separation_certificate import (
    SeparationCertificate,
    SeparationCheck,
    SeparationStatus,
    certify_many,
    certify_separation,
    verify_separation,
)
from planner_core.separation_pieces import (
    KNOT_TOL as KNOT_TOL,
)
from planner_core.separation_pieces import (
    SPEED_SAMPLES as SPEED_SAMPLES,
)
from planner_core.separation_pieces import (
    IntArray as IntArray,
)
from planner_core.separation_pieces import (
    common_knots as common_knots,
)
from planner_core.separation_pieces import (
    common_pieces,
    speed_bound,
)
from planner_core.separation_pieces import (
    max_margin_plane as max_margin_plane,
)
from planner_core.separation_pieces import (
    overlap as overlap,
)
from planner_core.separation_pieces import (
    pieces_on as pieces_on,
)
from planner_core.separation_pieces import (
    restrict as restrict,
)
from planner_core.separation_planning import (
    FAR as FAR,
)
from planner_core.separation_planning import (
    Neighbours,
    SeparationRows,
    bound_speed,
    near_pairs,
    neighbour_faces,
    planning_rows,
    separation_rows,
    with_neighbours,
)
from planner_core.separation_planning import (
    NoFace as NoFace,
)
from planner_core.separation_planning import (
    add_faces as add_faces,
)
from planner_core.separation_planning import (
    certify_all as certify_all,
)
from planner_core.separation_planning import (
    reference_points as reference_points,
)
from planner_core.separation_planning import (
    reference_trajectory as reference_trajectory,
)
from planner_core.separation_planning import (
    replace_message as replace_message,
)
from planner_core.separation_planning import (
    space_time_boxes as space_time_boxes,
)
from planner_core.separation_planning import (
    straight_reference as straight_reference,
)

__all__ = [
    "Neighbours",
    "SeparationCertificate",
    "SeparationCheck",
    "SeparationRows",
    "SeparationStatus",
    "bound_speed",
    "certify_many",
    "certify_separation",
    "common_pieces",
    "near_pairs",
    "neighbour_faces",
    "planning_rows",
    "separation_rows",
    "speed_bound",
    "verify_separation",
    "with_neighbours",
]
