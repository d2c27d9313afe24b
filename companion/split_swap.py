"""The one retry loop that swaps a new plan in at a split a little ahead of now.

Every plan made in flight (a mission's start, its anytime improvement, a change, a pop-up, a
fleet replan) is planned from a split ahead of now and swapped in through `Control.swap`, here
and nowhere else. The loop owns no state: it reads what is flown from `Control` and asks the
fleet (companion.deconfliction) to commit the candidate when there is one. What it does at each
turn (where to split, whether to plan again, move the plan later or give up, and what it says) is
decided by one pure function, companion.split_rules.split_step: the loop observes, calls it, shows
the call to the flight recorder (/navigator/split) and carries out the action.
"""

from __future__ import annotations

import itertools
import logging
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, replace
from typing import Any

from companion.config import Config
from companion.control import SWAP_LATE, Control
from companion.report import Reporter
from companion.route import Outcome
from companion.rule_run import RuleRun
from companion.split_rules import (
    Action,
    Again,
    Attempt,
    CheckHeld,
    Commit,
    Committed,
    Done,
    GiveUp,
    Held,
    Moved,
    MoveLater,
    Observation,
    PlanAt,
    Planned,
    Refused,
    SplitRules,
    SplitState,
    SwapDecided,
    TrySwap,
    first_state,
    split_step,
)
from companion.supervisor import Supervisor
from planner_core import Bounds, Trajectory, held_still, splice

log = logging.getLogger("companion")

# each call of the split's rules, shown to the flight recorder (companion.tap.Tap.split_step)
SplitObserver = Callable[[int, int, str, SplitRules, SplitState, Observation, SplitState, Action], None]


@dataclass(frozen=True)
class Swapped:
    """The end of `SplitSwap.at_split`: a plan swapped in (outcome, split time), or why not."""

    outcome: Outcome | None
    t_split: float = math.nan
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.outcome is not None and self.outcome.ok


def fleet_on(fleet: Any) -> bool:
    """`fleet` (companion.deconfliction.Deconfliction, or None) separates us from other vehicles."""
    return fleet is not None and bool(fleet.enabled)


def neighbours(fleet: Any, bounds: Bounds) -> Any:
    """The other vehicles' live trajectories for a plan in flight (None without a fleet)."""
    return fleet.neighbours(bounds) if fleet_on(fleet) else None


def logged(outcome: Outcome) -> Outcome:
    """An outcome, its planner bug (an exception turned into a refusal: companion.mission.answered)
    logged with its traceback: never swallowed silently."""
    bug = outcome.stats.get("internal_error")
    if bug:
        log.error("planner failed (answered as a refusal): %s\n%s", outcome.message, bug)
    return outcome


class SplitSwap:
    def __init__(self, cfg: Config, flight: Supervisor, control: Control, report: Reporter, fleet: Any) -> None:
        self.cfg = cfg
        self.flight = flight
        self.control = control
        self.report = report
        self.fleet = fleet  # companion.deconfliction.Deconfliction, or None without [fleet]
        self.calls = itertools.count(1)  # each at_split call's number, for the records of its steps
        # each call of the rules shown to the flight recorder: (call, step, what, rules, state
        # before, observation, state after, action); the service connects its tap
        self.observe: SplitObserver = lambda *_call: None

    async def at_split(self, what: str, arrived: float | None,
                       plan_at: Callable[[Trajectory, float], Awaitable[Outcome]],
                       hit: float | None = None, notes: list[str] | None = None,
                       ahead: float | None = None) -> Swapped:
        """Plan from a split `ahead` of now (default [planner] split_ahead) and swap the plan in.
        A plan that came after its split is planned again once, further ahead (from the time it
        took); a flown plan that changed while planning, once more. Each cause is said once, in
        its own words; the reason of a failure is the last cause. `plan_at(base, t_split)`.
        What to do at each turn is decided by companion.split_rules.split_step; this carries it out."""
        messages = notes if notes is not None else []

        def say(text: str) -> None:
            if text not in messages:
                messages.append(text)

        fleet = self.fleet if fleet_on(self.fleet) else None
        rules = SplitRules(self.cfg.planner.split_ahead if ahead is None else ahead, fleet is not None,
                           fleet.wait if fleet is not None else 0.0, hit)
        run = RuleRun(split_step, rules, first_state(rules), "split", next(self.calls),
                      lambda n, k, r, b, o, a, act: self.observe(n, k, what, r, b, o, a, act))

        def step(seen: Observation) -> Action:
            before = run.state
            action = run.step(seen)
            for text in run.state.said[len(before.said):]:
                say(text)
            return action

        control = self.control
        action: Action = Again()  # the first attempt
        base, route, outcome = control.active, control.route, None
        while True:
            if isinstance(action, Again | GiveUp) and action.cancel and fleet is not None:
                fleet.cancel()
            if isinstance(action, Again):
                if action.event:
                    self.report.event("fleet", action.event, what=what)
                base, route = control.active, control.route
                action = step(self._attempt())
            elif isinstance(action, PlanAt):
                assert base is not None
                t0 = time.monotonic()
                outcome = await plan_at(base, action.t_split)
                took = time.monotonic() - t0
                ok = outcome.ok and outcome.route is not None
                action = step(Planned(ok, outcome.message, took, control.active is base,
                                      control.active is not base or control.route is not route))
            elif isinstance(action, Commit):
                assert fleet is not None and outcome is not None and outcome.route is not None and base is not None
                why = await fleet.commit(splice(base, outcome.route.trajectory), what)
                action = step(Committed(why, fleet.clock_off is not None,
                                        control.active is not base or control.route is not route))
            elif isinstance(action, TrySwap):
                assert outcome is not None and outcome.route is not None and base is not None
                swapped = control.swap(splice(base, outcome.route.trajectory), action.t_split, arrived, what,
                                       outcome.route)
                if not swapped and action.cancel and fleet is not None:
                    fleet.cancel()  # the candidate that won is not flown: its number is not published
                refusal = "" if swapped else control.refusal
                action = step(SwapDecided(refusal, control.committed() if refusal == SWAP_LATE else None))
            elif isinstance(action, CheckHeld):
                assert base is not None
                action = step(Held(held_still(base, action.t_split, action.t_later)))
            elif isinstance(action, MoveLater):
                assert outcome is not None and outcome.route is not None and base is not None
                later = outcome.route.shifted(action.t_later - action.t_split)
                moved = control.swap(splice(base, later.trajectory), action.t_later, arrived, what, later)
                if moved:
                    outcome = replace(outcome, route=later)
                action = step(Moved("" if moved else control.refusal))
            elif isinstance(action, Done):
                if action.moved:
                    assert run.state.took is not None and run.state.t_split is not None
                    log.info("%s: planning took %.2f s, more than the %.2f s to its split time: the plan from the "
                             "hold starts %.2f s later", what, run.state.took, run.state.ahead, action.t_split - run.state.t_split)
                return Swapped(outcome, action.t_split)
            elif isinstance(action, Refused):
                assert run.state.t_split is not None
                return Swapped(outcome, run.state.t_split, action.reason)
            else:
                return Swapped(None, reason=action.reason)

    def _attempt(self) -> Attempt:
        """What each attempt starts from: in control (or the flight state), the time committed."""
        if not self.control.flying or not self.flight.flying_ours:
            return Attempt(False, self.flight.state.value, None)
        return Attempt(True, "", self.control.committed())
