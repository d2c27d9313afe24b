"""How long plans take in this service, and so how far ahead of now a new plan is split.

A plan in flight is spliced onto the flown one at a split time ahead of now; if it comes after
its split it cannot be flown. The split is chosen from the planning times measured here (a
running estimate per candidate plan per waypoint), and a search for the fastest durations is
capped to what fits before it. One owner: `PlanBudget` (held by the navigator).
"""

from __future__ import annotations

import numpy as np

from companion.config import Config
from planner_core import Bounds, Trajectory

FIXED_WAYPOINTS = 3  # a candidate plan's fixed cost (process hop, corridors, set-up), in waypoints' worth
LATE_MARGIN = 1.5  # the split is this many expected planning times ahead
RETRY_MARGIN = 2.0  # after a late plan: this many times the time it took (a loaded computer varies)
MAX_AHEAD = 30.0  # s: never further ahead (the old, verified plan flies on meanwhile)
SPLIT_FIT = 1.0  # a mission starts where the flown acceleration and jerk are within this share of its bounds
FULL_SEARCH = 40  # candidates: a cap this large is no cap (a small mission's whole search plans ~30)
MIN_CANDIDATES = 2  # the default allocation and one more (a long mission's local pass)


class PlanBudget:
    def __init__(self, cfg: Config) -> None:
        self.cfg = cfg
        # seconds per candidate plan per waypoint (FIXED_WAYPOINTS more) measured in this service: a
        # running estimate, up fast and down slowly; until warm-up, a guess on the slow side
        self.per_waypoint = 0.004

    def candidate_seconds(self, n_waypoints: int) -> float:
        """Expected wall time of one candidate plan of n waypoints in this service."""
        return self.per_waypoint * (max(n_waypoints, 1) + FIXED_WAYPOINTS)

    def split_ahead_for(self, n_waypoints: int, candidates: int = 1) -> float:
        """How far ahead of now a plan of n waypoints and that many candidate plans is split: the
        planning time expected from the ones measured in this service, with a margin, never less
        than [planner] split_ahead nor more than MAX_AHEAD."""
        expect = self.candidate_seconds(n_waypoints) * max(candidates, 1)
        return float(min(max(self.cfg.planner.split_ahead, LATE_MARGIN * expect + 0.05), MAX_AHEAD))

    def candidates_within(self, n_waypoints: int, seconds: float) -> int | None:
        """The fastest-allocation search's cap for a mission of n waypoints planned in `seconds`
        (None: no cap; never below MIN_CANDIDATES: a long mission then splits further ahead)."""
        k = int(max(seconds - 0.05, 0.0) / LATE_MARGIN / self.candidate_seconds(n_waypoints))
        return None if k >= FULL_SEARCH else max(k, MIN_CANDIDATES)

    def search_cap(self, n_waypoints: int) -> int:
        """The candidates a search of [planner] search_time plans here (MIN_CANDIDATES..FULL_SEARCH)."""
        fit = int(self.cfg.planner.search_time / self.candidate_seconds(n_waypoints))
        return min(max(fit, MIN_CANDIDATES), FULL_SEARCH)

    def mission_ahead(self, n_waypoints: int) -> float:
        """The first split of a mission flown now: as far ahead as a search of [planner]
        search_time takes here."""
        return self.split_ahead_for(n_waypoints, self.search_cap(n_waypoints))

    def measured(self, seconds: float, n_waypoints: int, candidates: int = 1) -> None:
        """A plan's wall time (queueing included) and its candidate plans into the running estimate."""
        per = seconds / max(candidates, 1) / (max(n_waypoints, 1) + FIXED_WAYPOINTS)
        # up at once (a plan that came late is planned again from this estimate: CI's runner
        # refused a mission whose retry, estimated at half the slowdown, was late again), down slowly
        a = 1.0 if per > self.per_waypoint else 0.2
        self.per_waypoint = (1 - a) * self.per_waypoint + a * per


def ahead_within(active: Trajectory, committed: float, bounds: Bounds, ahead: float, step: float = 0.05) -> float:
    """`ahead`, or further, to the first split (at most MAX_AHEAD past `committed`, the time up to
    which setpoints are sent) where the flown plan's velocity, acceleration and jerk are within
    `bounds` (velocity: within the 0.98 that start_mission clips it to): a mission with lower
    bounds than the flight (a = 3 sent while the vehicle accelerates at 4 m/s^2, or flies at
    3.7 m/s) cannot start from a jet beyond them at any duration, so it starts once the flown plan
    is back within them; where it never is, at `ahead` (and the refusal says the start is beyond
    the bounds)."""
    # every candidate split at once (one at a time: ~0.2 s of the event loop over 30 s ahead)
    ts = committed + ahead + step * np.arange(int((MAX_AHEAD - ahead) / step) + 1)
    inside = np.ones(ts.size, dtype=bool)
    for order, share in ((1, 0.98), (2, SPLIT_FIT), (3, SPLIT_FIT)):
        d = active.evaluate(np.minimum(ts, active.t_end), order)
        d[ts >= active.t_end] = 0.0  # at rest past its end (Control.jet)
        inside &= np.all((d >= share * bounds.lo[order - 1] - 1e-9) & (d <= share * bounds.hi[order - 1] + 1e-9),
                         axis=1)
    k = np.flatnonzero(inside)
    return ahead + step * int(k[0]) if k.size else ahead
