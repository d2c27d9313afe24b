"""How long plans take in this service, and so how far ahead of now a new plan is split.

A plan in flight is spliced onto the flown one at a split time ahead of now; if it comes after
its split it cannot be flown. The split is chosen from the planning times measured here (a
running estimate per candidate plan per waypoint), and a search for the fastest durations is
capped to what fits before it. One owner: `PlanBudget` (held by the navigator), whose every
question goes through one pure rule, `budget_step`, recorded on /navigator/budget and replayed
(companion/replay_budget.py).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

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

log = logging.getLogger("companion")


@dataclass(frozen=True)
class BudgetRules:
    """The configuration a budget answers with: [planner] split_ahead and search_time."""

    split_ahead: float
    search_time: float

    @staticmethod
    def of(cfg: Config) -> BudgetRules:
        return BudgetRules(float(cfg.planner.split_ahead), float(cfg.planner.search_time))


@dataclass(frozen=True)
class Budget:
    """What the budget learns: seconds per candidate plan per waypoint (FIXED_WAYPOINTS more)
    measured in this service, a running estimate, up fast and down slowly; until warm-up, a
    guess on the slow side."""

    per_waypoint: float = 0.004


# What a budget is asked (each answered by `budget_step`; `Measured` alone changes it)
@dataclass(frozen=True)
class SplitAhead:
    """How far ahead of now a plan of n waypoints and that many candidate plans is split."""

    n_waypoints: int
    candidates: int = 1


@dataclass(frozen=True)
class CandidatesWithin:
    """The fastest-allocation search's cap for n waypoints planned in `seconds`."""

    n_waypoints: int
    seconds: float


@dataclass(frozen=True)
class SearchCap:
    """The candidates a search of [planner] search_time plans here."""

    n_waypoints: int


@dataclass(frozen=True)
class MissionAhead:
    """The first split of a mission flown now."""

    n_waypoints: int


@dataclass(frozen=True)
class Measured:
    """A plan's wall time (queueing included) and its candidate plans."""

    seconds: float
    n_waypoints: int
    candidates: int = 1


Ask = SplitAhead | CandidatesWithin | SearchCap | MissionAhead | Measured
Answer = float | int | None


def candidate_seconds(budget: Budget, n_waypoints: int) -> float:
    """Expected wall time of one candidate plan of n waypoints in this service."""
    return budget.per_waypoint * (max(n_waypoints, 1) + FIXED_WAYPOINTS)


def _split_ahead(rules: BudgetRules, budget: Budget, n_waypoints: int, candidates: int) -> float:
    # the planning time expected, with a margin, never less than split_ahead nor more than MAX_AHEAD
    expect = candidate_seconds(budget, n_waypoints) * max(candidates, 1)
    return float(min(max(rules.split_ahead, LATE_MARGIN * expect + 0.05), MAX_AHEAD))


def _search_cap(rules: BudgetRules, budget: Budget, n_waypoints: int) -> int:
    fit = int(rules.search_time / candidate_seconds(budget, n_waypoints))
    return min(max(fit, MIN_CANDIDATES), FULL_SEARCH)


def budget_step(rules: BudgetRules, budget: Budget, ask: Ask) -> tuple[Budget, Answer]:
    """The budget's one rule: its answer to `ask`, and the budget after (changed by `Measured`
    only). Pure, so the flight recorder's calls (/navigator/budget) replay."""
    if isinstance(ask, SplitAhead):
        return budget, _split_ahead(rules, budget, ask.n_waypoints, ask.candidates)
    if isinstance(ask, CandidatesWithin):
        # None: no cap; never below MIN_CANDIDATES (a long mission then splits further ahead)
        k = int(max(ask.seconds - 0.05, 0.0) / LATE_MARGIN / candidate_seconds(budget, ask.n_waypoints))
        return budget, None if k >= FULL_SEARCH else max(k, MIN_CANDIDATES)
    if isinstance(ask, SearchCap):
        return budget, _search_cap(rules, budget, ask.n_waypoints)
    if isinstance(ask, MissionAhead):  # as far ahead as a search of search_time takes here
        return budget, _split_ahead(rules, budget, ask.n_waypoints, _search_cap(rules, budget, ask.n_waypoints))
    per = ask.seconds / max(ask.candidates, 1) / (max(ask.n_waypoints, 1) + FIXED_WAYPOINTS)
    # up at once (a plan that came late is planned again from this estimate: CI's runner refused
    # a mission whose retry, estimated at half the slowdown, was late again), down slowly
    a = 1.0 if per > budget.per_waypoint else 0.2
    return Budget((1 - a) * budget.per_waypoint + a * per), None


BudgetObserver = Callable[[Budget, Ask, Budget, Answer], None]


def _unobserved(_before: Budget, _ask: Ask, _after: Budget, _answer: Answer) -> None:
    pass


class PlanBudget:
    """The budget's one owner (held by the navigator): each question goes through `budget_step`
    and is shown to `observe` (the flight recorder's tap: it must return at once)."""

    def __init__(self, cfg: Config) -> None:
        self.rules = BudgetRules.of(cfg)
        self.state = Budget()
        self.observe: BudgetObserver = _unobserved

    @property
    def per_waypoint(self) -> float:
        return self.state.per_waypoint

    def _ask(self, ask: Ask) -> Answer:
        before = self.state
        self.state, answer = budget_step(self.rules, before, ask)
        try:
            self.observe(before, ask, self.state, answer)
        except Exception:  # a recorder's fault must never change a plan
            log.exception("plan budget: the observer failed")
        return answer

    def candidate_seconds(self, n_waypoints: int) -> float:
        return candidate_seconds(self.state, n_waypoints)

    def split_ahead_for(self, n_waypoints: int, candidates: int = 1) -> float:
        """How far ahead of now a plan of n waypoints and that many candidate plans is split: the
        planning time expected from the ones measured in this service, with a margin, never less
        than [planner] split_ahead nor more than MAX_AHEAD."""
        return float(self._ask(SplitAhead(n_waypoints, candidates)))  # type: ignore[arg-type]

    def candidates_within(self, n_waypoints: int, seconds: float) -> int | None:
        """The fastest-allocation search's cap for a mission of n waypoints planned in `seconds`
        (None: no cap; never below MIN_CANDIDATES: a long mission then splits further ahead)."""
        answer = self._ask(CandidatesWithin(n_waypoints, float(seconds)))
        return None if answer is None else int(answer)

    def search_cap(self, n_waypoints: int) -> int:
        """The candidates a search of [planner] search_time plans here (MIN_CANDIDATES..FULL_SEARCH)."""
        return int(self._ask(SearchCap(n_waypoints)))  # type: ignore[arg-type]

    def mission_ahead(self, n_waypoints: int) -> float:
        """The first split of a mission flown now: as far ahead as a search of [planner]
        search_time takes here."""
        return float(self._ask(MissionAhead(n_waypoints)))  # type: ignore[arg-type]

    def measured(self, seconds: float, n_waypoints: int, candidates: int = 1) -> None:
        """A plan's wall time (queueing included) and its candidate plans into the running estimate."""
        self._ask(Measured(float(seconds), n_waypoints, candidates))


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
