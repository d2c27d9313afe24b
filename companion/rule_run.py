"""One run of a pure decision rule, stepped in one place.

The service's decisions are pure functions `rule(rules, state, observation) -> (state, action)`
(companion/*_rules.py); the shell that observes and carries out holds one `RuleRun` per run (a
command sequence, a pop-up's race, a split, a hold watched, the stall watch): it keeps the state,
steps it, and shows each call to the flight recorder with the run's number and the step's within
it. An observer's fault is logged and never changes the decision.
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable
from typing import Generic, TypeVar

log = logging.getLogger("companion")

R = TypeVar("R")  # the run's rules (fixed for the run)
S = TypeVar("S")  # the rule's state
O = TypeVar("O")  # noqa: E741 - an observation
A = TypeVar("A")  # an action

Observer = Callable[[int, int, R, S, O, S, A], None]  # (run, step, rules, before, seen, after, action)


class RuleRun(Generic[R, S, O, A]):
    """`rule` stepped from `state` under `rules`; run number `number` (0: a run no observer
    sees); `what` names it in the log. `shown(before, seen, after, action)` says which calls
    the observer sees (default: all)."""

    def __init__(self, rule: Callable[[R, S, O], tuple[S, A]], rules: R, state: S, what: str, number: int = 0,
                 observe: Observer[R, S, O, A] | None = None,
                 shown: Callable[[S, O, S, A], bool] | None = None) -> None:
        self.rule = rule
        self.rules = rules
        self.state = state
        self.what = what
        self.number = number
        self.observe = observe
        self.shown = shown
        self._steps = itertools.count(1)

    def step(self, seen: O) -> A:
        before = self.state
        self.state, action = self.rule(self.rules, before, seen)
        if self.observe is not None and (self.shown is None or self.shown(before, seen, self.state, action)):
            try:
                self.observe(self.number, next(self._steps), self.rules, before, seen, self.state, action)
            except Exception:  # a recorder's fault must never change what is flown
                log.exception("%s: the observer failed", self.what)
        return action


class Runs(Generic[R, S, O, A]):
    """Numbered runs of one rule, each shown to the one observer (the service connects the tap)."""

    def __init__(self, rule: Callable[[R, S, O], tuple[S, A]], what: str) -> None:
        self.rule = rule
        self.what = what
        self.numbers = itertools.count(1)
        self.observe: Observer[R, S, O, A] | None = None

    def run(self, rules: R, state: S) -> RuleRun[R, S, O, A]:
        return RuleRun(self.rule, rules, state, self.what, next(self.numbers), self.observe)
