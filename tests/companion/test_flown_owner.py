"""One owner of what is flown (issue 22, item 2): `Control` changes the mission's route with the
trajectory and its time base, one method per change; no other part writes either half."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule

from companion.braking import StopGuard
from companion.control import Control
from companion.navigator import Navigator
from companion.route import Route
from companion.setpoints import Feed, YawPolicy
from planner_core import hold
from tests.companion.test_route import fly

COMPANION = Path(__file__).resolve().parents[2] / "companion"
# two routes planned once (the owner does not plan: it keeps what it is given)
ROUTES: list[Route] = [fly([[0.0, 6.0, -1.5], [4.0, 6.0, -1.5]], [0.0, 0.0, -1.5], t0=0.0),
                       fly([[3.0, 0.0, -1.5]], [0.0, 0.0, -1.5], t0=0.0)]


class Target:
    feed: Feed | None = None


class FlownMachine(RuleBasedStateMachine):
    """take / swap (with a route, or a stop) / hold / pause / release / forget / load in any
    order: the route is flown only on the trajectory it was swapped in with; released means
    neither a route nor a trajectory nor a time base nor a feed."""

    @initialize()
    def fresh(self) -> None:
        self.target = Target()
        self.ctl = Control(self.target, lambda sp: None, YawPolicy("fixed", 0.0, 0.5), 50.0)
        self.route: Route | None = None  # what the route should be (the model)

    def _here(self) -> np.ndarray:
        return np.asarray(self.ctl.jet(self.ctl.now())[0], dtype=float)

    @rule(x=st.floats(-5.0, 5.0), y=st.floats(-5.0, 5.0))
    def take(self, x: float, y: float) -> None:
        self.ctl.take(np.array([x, y, -1.5]), 0.0, "test")
        self.route = None
        assert self.ctl.streaming and self.ctl.flying

    @precondition(lambda self: self.ctl.flying)
    @rule(which=st.sampled_from([0, 1, None]))
    def swap(self, which: int | None) -> None:
        route = None if which is None else ROUTES[which]
        was, interrupted = self.route, self.ctl.interrupted
        now = self.ctl.now()
        # the flown plan continued (a hold where it is): passes the owner's check
        ok = self.ctl.swap(hold(self._here(), now), now + 0.05, None, "test", route)
        assert ok, self.ctl.refusal
        self.route = route
        if route is not None:
            assert self.ctl.interrupted is None  # the mission is flown again
        elif was is None:
            assert self.ctl.interrupted is interrupted  # nothing was flown to interrupt
        else:
            assert self.ctl.interrupted is not None  # a stop: what is left waits for `resume`

    @precondition(lambda self: not self.ctl.flying)
    @rule()
    def swap_without_control(self) -> None:
        assert not self.ctl.swap(hold(np.zeros(3), 0.0), 1.0, None, "test", ROUTES[0])
        assert self.ctl.route is None and self.ctl.active is None

    @precondition(lambda self: self.ctl.flying)
    @rule(dx=st.floats(-1.0, 1.0))
    def hold_here(self, dx: float) -> None:
        was = self.route
        self.ctl.hold_here(self._here() + np.array([dx, 0.0, 0.0]))
        self.route = None
        if was is not None:
            assert self.ctl.interrupted is not None

    @precondition(lambda self: self.ctl.flying)
    @rule()
    def pause(self) -> None:
        active = self.ctl.active
        self.ctl.pause()
        assert self.ctl.active is active and not self.ctl.streaming and self.target.feed is None

    @rule()
    def release(self) -> None:
        had = self.route is not None or self.ctl.interrupted is not None
        self.ctl.release()
        self.route = None
        assert self.ctl.active is None and self.ctl.t_base is None and not self.ctl.streaming
        assert self.ctl.interrupted is None and self.target.feed is None
        if had:
            assert self.ctl.pending is not None  # what was left waits for `start`

    @rule()
    def forget(self) -> None:
        active = self.ctl.active
        self.ctl.forget()
        self.route = None
        assert self.ctl.active is active  # flies on until changed (a stop, a release)
        assert self.ctl.pending is None and self.ctl.interrupted is None

    @rule(which=st.sampled_from([0, 1]))
    def load(self, which: int) -> None:
        spec = ROUTES[which].mission
        self.ctl.load(spec)
        assert self.ctl.pending is spec
        self.ctl.unload(spec)
        assert self.ctl.pending is None

    @invariant()
    def route_and_trajectory_agree(self) -> None:
        ctl = self.ctl
        assert ctl.agrees()
        assert ctl.route is self.route
        if ctl.route is not None:
            assert ctl.active is not None and ctl.t_base is not None
        if ctl.active is None:  # released: neither
            assert ctl.route is None and ctl.t_base is None and not ctl.streaming and self.target.feed is None
        feed = self.target.feed
        if feed is not None:
            assert feed.trajectory is ctl.active and feed.t_base == ctl.t_base and ctl.streaming


TestFlown = FlownMachine.TestCase
TestFlown.settings = settings(max_examples=40, stateful_step_count=25, deadline=None,
                              suppress_health_check=[HealthCheck.too_slow])


def _sources() -> dict[str, str]:
    return {str(p.relative_to(COMPANION)): p.read_text() for p in COMPANION.rglob("*.py")}


def test_no_part_but_control_changes_one_half_of_what_is_flown() -> None:
    # no release of the mission apart from the trajectory (the navigator's is gone)
    assert not hasattr(Navigator, "release") and not hasattr(Navigator, "forget")
    for name in ("route", "pending", "interrupted"):
        prop = inspect.getattr_static(Navigator, name)
        assert isinstance(prop, property) and prop.fset is None, name
    for prop_name in ("route", "pending", "interrupted", "active", "t_base", "streaming"):
        prop = inspect.getattr_static(Control, prop_name)
        assert isinstance(prop, property) and prop.fset is None, prop_name
    halves = re.compile(r"\b(?:nav|navigator)\.(?:release|forget)\(|"  # the old half-releases
                        r"\b(?:self|nav|navigator|control|ctl)\.(?:route|pending|interrupted)\s*=[^=]|"
                        r"\b(?:control|ctl)\._|"  # the owner's private state or its _set
                        r"\.feed\s*=[^=]")  # the setpoint thread's feed: Control._set writes it
    found = [f"{path}:{n}: {line.strip()}" for path, text in _sources().items() if path != "control.py"
             for n, line in enumerate(text.splitlines(), 1) if halves.search(line)]
    assert not found, found


def test_the_braking_deadline_and_the_lead_have_one_writer_each() -> None:
    prop = inspect.getattr_static(StopGuard, "deadline")
    assert isinstance(prop, property) and prop.fset is None
    src = _sources()
    deadline = [p for p, t in src.items() if re.search(r"\.deadline\s*=[^=]", t)]
    assert deadline == [], deadline
    lead = [(p, line.strip()) for p, t in src.items() for line in t.splitlines()
            if re.search(r"\.lead\s*=[^=]", line) and not line.strip().startswith(("#", '"', "`"))
            and "setpoints.lead =" not in line]
    # the sender's own initial zero, and Tracking._set_lead
    assert sorted(lead) == [("setpoints.py", "self.lead = 0.0  # s: setpoints are sampled this far ahead on the "
                                             "trajectory (lag compensation)"),
                            ("tracking.py", "self.lead_target.lead = lead")], lead
