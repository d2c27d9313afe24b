"""The fleet frame: where this autopilot's local NED frame sits in the fleet's (issue 24.2).

`[fleet] origin = [lat, lon, alt]` defines the fleet frame (NED / ENU metres about that point,
the tangent plane there: companion.geodesy). The autopilot's local frame is placed in it from,
in this order of preference:

1. `[fleet] offset_ned`: configured (a vehicle without GPS; the local origin measured in the
   fleet frame). Axes taken parallel to the fleet's.
2. GPS_GLOBAL_ORIGIN: the local frame's geodetic origin, as the autopilot reports it (PX4 once
   its estimator has a global origin, ArduPilot once its EKF origin is set; both on request).
3. HOME_POSITION: home geodetic and in the local frame, hence the local origin.

Until one of them is known the frame is not placed: messages with `"origin": "fleet"` are
refused with the reason, status `fleet` says it (`placed: false`, `reason`), and an event
`fleet_frame` says each change (placed, moved, lost). One owner: this module's `FleetFrame`;
the service asks it, nothing else writes it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from companion.config import FleetConfig
from companion.geodesy import Placement, lla_to_ned, local_origin_from_home, placement

# A local origin further than this from the fleet origin is another site (or a wrong origin):
# tangent planes so far apart are not a frame to fly a fleet in.
MAX_DISTANCE_M = 50_000.0
# A placement that moves less than this is the same one (an autopilot's origin re-sent, rounded
# to 1e-7 degrees and a millimetre).
SAME_M = 0.02


class FleetFrame:
    def __init__(self, cfg: FleetConfig) -> None:
        self.cfg = cfg
        self.enabled = bool(cfg.origin)
        self.placement: Placement | None = None
        self.reason = ("waiting for the autopilot's GPS_GLOBAL_ORIGIN or HOME_POSITION (requested at link-up)"
                       if self.enabled else "no [fleet] origin configured")
        if self.enabled and cfg.offset_ned:
            self.placement = Placement(np.asarray(cfg.offset_ned, dtype=float), source="offset_ned")
            self.reason = ""

    def update(self, gps_origin: tuple[float, float, float] | None, home_lla: tuple[float, float, float] | None,
               home_local: Any) -> str | None:
        """Recompute from what the autopilot reported; a sentence for an event when the placement
        changed (placed, moved, or could not be made), None when it did not."""
        if not self.enabled or self.cfg.offset_ned:
            return None
        origin = self.cfg.origin
        new: Placement | None = None
        why = ""
        if gps_origin is not None:
            local, source = gps_origin, "gps_global_origin"
        elif home_lla is not None and home_local is not None:
            local, source = local_origin_from_home(home_lla, home_local), "home_position"
        else:
            return None  # nothing new to place by
        distance = float(np.linalg.norm(lla_to_ned(local, origin)))
        if distance > MAX_DISTANCE_M:
            why = (f"the autopilot's local origin ({source}: {local[0]:.7f}, {local[1]:.7f}, {local[2]:.1f} m) is "
                   f"{distance / 1000:.0f} km from [fleet] origin: another site, or a wrong origin (at most "
                   f"{MAX_DISTANCE_M / 1000:.0f} km)")
        else:
            new = placement(local, origin, source)
        old = self.placement
        if new is None:
            if old is None and why == self.reason:
                return None
            self.placement, self.reason = None, why
            return f"fleet frame: cannot place this vehicle: {why}"
        self.placement, self.reason = new, ""
        if old is not None and float(np.linalg.norm(old.offset - new.offset)) < SAME_M and old.source == new.source:
            self.placement = old  # the same: keep the first (no event for rounding)
            return None
        off = ", ".join(f"{v:.2f}" for v in new.offset)
        if old is None:
            return f"fleet frame placed from {source}: the local origin is at [{off}] m NED in the fleet frame"
        moved = float(np.linalg.norm(old.offset - new.offset))
        return (f"fleet frame moved by {moved:.2f} m ({source}; the autopilot's origin changed: a reset or a "
                f"reboot): the local origin is now at [{off}] m NED in the fleet frame")

    def for_messages(self) -> Placement | str | None:
        """What `wire.messages.read` needs: the placement, the reason there is none, or None (no fleet)."""
        if not self.enabled:
            return None
        return self.placement if self.placement is not None else self.reason

    def status(self) -> dict[str, Any] | None:
        """Status `fleet`: None without [fleet] origin."""
        if not self.enabled:
            return None
        p = self.placement
        return {
            "origin": list(self.cfg.origin),
            "placed": p is not None,
            "frame": "placed" if p is not None else "unknown",
            "source": None if p is None else p.source,
            # the local origin in the fleet frame (NED, m), and the local axes in fleet axes (rows)
            "offset_ned": None if p is None else [round(float(v), 3) for v in p.offset],
            "rotation": None if p is None else [[round(float(v), 9) for v in row] for row in p.rotation],
            "reason": self.reason or None,
            "clock_tolerance": self.cfg.clock_tolerance,
        }
