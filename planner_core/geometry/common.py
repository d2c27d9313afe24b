"""What every geometry module shares: the corridor error, the certificate's tolerance, array aliases."""


from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from planner_core.errors import FieldError

IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

CERT_TOL = 1e-10  # slack on the certificate test; the offsets are exact up to rounding


class CorridorError(FieldError):
    """No safe convex corridor exists; names the segment/waypoint/obstacle at fault.

    A `FieldError` whose message is the description given (unchanged), whose
    `.reason` is that description and whose `.field` is "segments[j]" for a
    blocked segment, else "waypoints[i]" for a waypoint at fault, else "corridors".
    """

    def __init__(
        self,
        message: str,
        *,
        segment: int | None = None,
        waypoint: int | None = None,
        obstacle: int | None = None,
    ) -> None:
        if segment is not None:
            where = f"segments[{segment}]"
        elif waypoint is not None:
            where = f"waypoints[{waypoint}]"
        else:
            where = "corridors"
        super().__init__(where, message, message=message)
        self.segment = segment
        self.waypoint = waypoint
        self.obstacle = obstacle
