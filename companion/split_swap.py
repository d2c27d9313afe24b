"""The one retry loop that swaps a new plan in at a split a little ahead of now.

Every plan made in flight (a mission's start, its anytime improvement, a change, a pop-up, a
fleet replan) is planned from a split ahead of now and swapped in through `Control.swap`, here
and nowhere else. The loop owns no state: it reads what is flown from `Control` and asks the
fleet (companion.deconfliction) to commit the candidate when there is one.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, replace
from typing import Any

from companion.config import Config
from companion.control import SWAP_LATE, Control
from companion.plan_budget import MAX_AHEAD, RETRY_MARGIN
from companion.report import Reporter
from companion.route import Outcome
from companion.supervisor import Supervisor
from planner_core import Bounds, Trajectory, held_still, splice

log = logging.getLogger("companion")

FLEET_TRIES = 8  # candidates that lost to other vehicles before a plan is given up (docs/fleet.md)


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

    async def at_split(self, what: str, arrived: float | None,
                       plan_at: Callable[[Trajectory, float], Awaitable[Outcome]],
                       hit: float | None = None, notes: list[str] | None = None,
                       ahead: float | None = None) -> Swapped:
        """Plan from a split `ahead` of now (default [planner] split_ahead) and swap the plan in.
        A plan that came after its split is planned again once, further ahead (from the time it
        took); a flown plan that changed while planning, once more. Each cause is said once, in
        its own words; the reason of a failure is the last cause. `plan_at(base, t_split)`."""
        messages = notes if notes is not None else []

        def say(text: str) -> None:
            if text not in messages:
                messages.append(text)

        fleet = self.fleet if fleet_on(self.fleet) else None
        ahead = self.cfg.planner.split_ahead if ahead is None else ahead
        if fleet is not None:  # a plan is proposed, then committed 2 x max_delay later (companion.commit)
            ahead += fleet.wait
        late = changed = lost = 0
        reason = ""
        while late < 2 and changed < 2:
            if not self.control.flying or not self.flight.flying_ours:
                return Swapped(None, reason=f"no longer in control ({self.flight.state.value})")
            base, route = self.control.active, self.control.route
            assert base is not None
            t_split = self.control.committed() + ahead  # setpoints up to now + lead are sent
            if hit is not None and t_split >= hit:
                reason = "too close to the obstacle to replan"
                say(reason)
                break
            t0 = time.monotonic()
            outcome = await plan_at(base, t_split)
            took = time.monotonic() - t0
            if not outcome.ok or outcome.route is None:
                return Swapped(outcome, t_split, outcome.message)
            if fleet is not None and self.control.active is base:
                why = await fleet.commit(splice(base, outcome.route.trajectory), what)
                if why is not None and fleet.clock_off is not None:
                    reason = why  # planning again would not help
                    say(why)
                    break
                if why is not None:
                    lost += 1
                    reason = why
                    say(why + ("; planning again against it" if lost < FLEET_TRIES else ""))
                    if lost >= FLEET_TRIES:
                        break
                    self.report.event("fleet", f"deconfliction: {why}; planning again against it", what=what)
                    continue
            if self.control.active is not base or self.control.route is not route:
                if fleet is not None:
                    fleet.cancel()
                changed += 1
                reason = "the flown plan changed while planning (a stop or another change came first)"
                say(reason + "; planning again")
                continue
            if self.control.swap(splice(base, outcome.route.trajectory), t_split, arrived, what, outcome.route):
                return Swapped(outcome, t_split)
            if fleet is not None:
                fleet.cancel()  # the candidate that won is not flown: its number is not published
            if self.control.refusal != SWAP_LATE:
                reason = self.control.refusal  # an internal check: planning again would not help
                say(reason)
                break
            # late, from a hold: the same plan starts later just as well (the curve and its checks
            # do not depend on the time; a fleet's separation does): moved, not planned again
            t_later = self.control.committed() + min(max(2.0 * ahead, RETRY_MARGIN * took + 0.1), MAX_AHEAD)
            if fleet is None and held_still(base, t_split, t_later):
                later = outcome.route.shifted(t_later - t_split)
                if self.control.swap(splice(base, later.trajectory), t_later, arrived, what, later):
                    log.info("%s: planning took %.2f s, more than the %.2f s to its split time: the plan from the "
                             "hold starts %.2f s later", what, took, ahead, t_later - t_split)
                    return Swapped(replace(outcome, route=later), t_later)
            late += 1
            reason = (f"planning took {took:.2f} s, more than the {ahead:.2f} s to its split time"
                      + (" twice: the computer is too busy to plan this in flight now" if late == 2 else ""))
            if late < 2:
                say(reason + "; planned again once, further ahead")
                ahead = min(max(2.0 * ahead, RETRY_MARGIN * took + 0.1), MAX_AHEAD)
            else:
                say(reason)
        return Swapped(None, reason=reason or "too close")
