"""Issue 21.8 / 20.5: valid missions of 5-300 waypoints sent in flight, one every 1.5 s, are
all planned and flown (none refused for lack of time) while a CPU hog spins beside the test;
the split time follows the planning time measured in the service. And each cause of a refused
swap has its own reason, said once."""

from __future__ import annotations

import asyncio
import json
import math
import subprocess
import sys
import time
from functools import partial
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from companionkit import Events, service_for, serving, until

from companion.config import Config
from companion.control import SWAP_DIFFERS, SWAP_LATE
from companion.mission_start import MissionStart
from companion.plan_budget import FULL_SEARCH, LATE_MARGIN, MAX_AHEAD, MIN_CANDIDATES, PlanBudget
from companion.route import Outcome
from companion.split_swap import SplitSwap
from companion.wire.messages import read
from sitl_mock import MockAutopilot, MockConfig


def mission(mid: str, n: int, phase: float) -> bytes:
    """n waypoints 2 m apart, a lawn-mower pattern of rows of 8 from near the origin at 2 m up
    (`phase` shifts it sideways); a long one flies for minutes: the next one replaces it."""
    k = np.arange(n)
    row, col = k // 8, k % 8
    col = np.where(row % 2 == 1, 7 - col, col)
    wps = np.stack([2.0 * col - 7.0 + phase, 2.0 * row + 1.0, np.full(n, -2.0)], axis=1).round(3).tolist()
    return json.dumps({"id": mid, "waypoints": wps}).encode()


@pytest.fixture(params=[False, True], ids=["quiet", "cpu_hog"])
def cpu_hog(request: pytest.FixtureRequest) -> Any:
    """A process spinning on one core for the test's duration (normal scheduling), or none."""
    if not request.param:
        yield None
        return
    proc = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        yield proc
    finally:
        proc.kill()
        proc.wait()


@pytest.mark.slow
def test_missions_replaced_in_flight_are_all_flown(tmp_path: Path, cpu_hog: Any) -> None:
    """Each mission is sent 1.5 s after the previous one, or once that one is answered if it
    takes longer (an operator replacing missions as fast as they are taken)."""
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"],
                                    log_path=str(tmp_path / "f.jsonl"))).start()
    sizes = [5, 40, 5, 300, 20, 5]
    stalled: list[str] = []

    async def go() -> None:
        svc = service_for(mock, planner={"executor": "process"})
        events = Events(svc)

        def answered(mid: str) -> bool:
            return any(e.get("mission") == mid for e in events.of("accepted") + events.of("rejected"))

        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 20, "position")
            await svc.commands.takeoff(2.0)
            ids = [f"m{i}-{n}" for i, n in enumerate(sizes)]
            try:
                for i, (mid, n) in enumerate(zip(ids, sizes, strict=True)):
                    sent = time.monotonic()
                    svc.inbound.dispatch("mission", b"", sent, read("mission", mission(mid, n, 0.7 * i), svc.cfg))
                    await until(lambda mid=mid: answered(mid), 150, f"mission {mid} answered")  # type: ignore[misc]
                    await asyncio.sleep(max(0.0, 1.5 - (time.monotonic() - sent)))
                await until(lambda: any(e.get("mission") == ids[-1] for e in events.of("mission_complete")), 60,
                            "the last mission flown to its end")
            except AssertionError as exc:
                if not events.of("stalled"):
                    for e in events.all:
                        print(e["type"], e.get("message", "")[:300])
                    # the answers in the failure's own line: a CI log keeps only part of the output
                    answers = [f"{e['type']}: {e.get('message', '')[:160]}" for e in events.all
                               if e["type"] in ("accepted", "rejected") and e.get("mission") in ids[-2:]]
                    raise AssertionError(f"{exc}; the last two missions' answers: {answers}") from None
            stalled.extend(e["message"] for e in events.of("stalled"))
            if stalled:
                return
            rejected = [e["message"] for e in events.of("rejected")]
            assert not rejected, rejected
            flown = [e["mission"] for e in events.of("accepted") if e.get("mission") in ids]
            assert flown == ids, flown  # in order, each planned and swapped in
            print(f"estimated plan time per waypoint {svc.navigator.budget.per_waypoint * 1000:.1f} ms; "
                  f"split ahead for 5 / 300 waypoints: {svc.navigator.budget.split_ahead_for(5):.2f} / "
                  f"{svc.navigator.budget.split_ahead_for(300):.2f} s; "
                  f"plans (ms): {[e.get('plan_ms') for e in events.of('accepted')]}")

    try:
        asyncio.run(go())
    finally:
        mock.stop()
    if stalled:
        # the setpoint stream starved by the load (issue 21.7, not this test's subject): the
        # companion released control, as it must; what missions do then is not in question
        pytest.xfail(f"setpoint thread starved under load (issue 21.7): {stalled[0][:200]}")


# -- the retry loop's reasons, on its own -----------------------------------------------------


class _Control:
    def __init__(self, refusals: list[str]) -> None:
        self.refusals = refusals
        self.active: Any = object()
        self.route: Any = None  # the mission flown (Control holds it)
        self.flying = True
        self.refusal = ""
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def committed(self) -> float:  # no lead in this fake: what was sent ends now
        return self.t

    def swap(self, *_: Any) -> bool:
        self.refusal = self.refusals.pop(0) if self.refusals else ""
        return not self.refusal


def _navigator(refusals: list[str]) -> Any:
    """What the retry loop (companion.split_swap) and a mission's split (MissionStart) read."""
    cfg = Config()
    control = _Control(refusals)
    flight = SimpleNamespace(flying_ours=True, state=SimpleNamespace(value="STREAMING"))
    # no [fleet]: no commit wait in the replan loop
    nav = SimpleNamespace(cfg=cfg, control=control, flight=flight, budget=PlanBudget(cfg),
                          swap=SplitSwap(cfg, flight, control, None, None))  # type: ignore[arg-type]
    nav.ahead_within = partial(MissionStart.ahead_within, nav)
    return nav


def _run(nav: Any, aheads: list[float], held: bool = False) -> Any:
    """The retry loop with a flown plan that moves (or, `held`, holds still) at the split."""
    async def plan_at(_base: Any, t_split: float) -> Outcome:
        aheads.append(t_split)
        await asyncio.sleep(0.01)
        route = SimpleNamespace(trajectory=None, shifted=lambda dt: SimpleNamespace(trajectory=None, dt=dt))
        return Outcome(True, route=route)  # type: ignore[arg-type]

    import companion.split_swap as swapmod

    splice, swapmod.splice = swapmod.splice, lambda a, b: b  # type: ignore[assignment]
    still, swapmod.held_still = swapmod.held_still, lambda *_: held  # type: ignore[assignment]
    try:
        notes: list[str] = []
        return asyncio.run(nav.swap.at_split("mission x", None, plan_at, notes=notes)), notes
    finally:
        swapmod.splice = splice
        swapmod.held_still = still


def test_a_swap_refused_by_the_check_says_so_once_not_the_split_time() -> None:
    done, notes = _run(_navigator([SWAP_DIFFERS, SWAP_DIFFERS, SWAP_DIFFERS]), [])
    assert not done.ok and done.reason == SWAP_DIFFERS and notes == [SWAP_DIFFERS]
    assert "split time" not in done.reason


def test_a_late_plan_is_planned_again_once_further_ahead() -> None:
    aheads: list[float] = []
    done, notes = _run(_navigator([SWAP_LATE]), aheads)
    assert done.ok and len(aheads) == 2 and aheads[1] > aheads[0]
    assert len(notes) == 1 and "planned again once, further ahead" in notes[0]
    aheads.clear()
    done, notes = _run(_navigator([SWAP_LATE, SWAP_LATE, SWAP_LATE]), aheads)
    assert not done.ok and len(aheads) == 2 and "twice" in done.reason and len(notes) == 2


def test_a_late_plan_from_a_hold_is_moved_to_a_later_split_not_planned_again() -> None:
    aheads: list[float] = []
    done, notes = _run(_navigator([SWAP_LATE]), aheads, held=True)
    assert done.ok and len(aheads) == 1 and not notes  # planned once
    assert done.t_split > aheads[0] and done.outcome.route.dt == pytest.approx(done.t_split - aheads[0])


def test_the_split_follows_the_measured_planning_time() -> None:
    nav = _navigator([])
    floor = nav.cfg.planner.split_ahead
    assert floor <= nav.budget.split_ahead_for(5) < 0.2  # idle: about the configured split
    for _ in range(5):
        nav.budget.measured(1.0, 5)  # a loaded machine: 1 s for 5 waypoints
    assert nav.budget.split_ahead_for(5) >= 1.4 and nav.budget.split_ahead_for(300) == MAX_AHEAD
    for _ in range(40):
        nav.budget.measured(0.03, 5)
    assert nav.budget.split_ahead_for(5) < 0.3 and math.isfinite(nav.budget.per_waypoint)


def test_the_search_is_cut_to_what_fits_before_the_split() -> None:
    """Issue 25 / 21: on a quiet computer a small mission's search runs whole; on a loaded one
    (1 s measured for one candidate of 5 waypoints) it is cut to what fits in the split the
    navigator chose, so a mission in flight is answered instead of refused as too late; a long
    mission keeps at least the default allocation and its local pass, and splits further ahead."""
    nav = _navigator([])
    for _ in range(20):
        nav.budget.measured(0.05, 5, 8)  # ~6 ms a candidate: a quiet 2-core machine, numpy path
    ahead = nav.budget.mission_ahead(5)
    assert nav.budget.candidates_within(5, ahead) is None and ahead < 1.0
    for _ in range(5):
        nav.budget.measured(1.0, 5, 1)  # a busy one
    ahead = nav.budget.mission_ahead(5)
    cap = nav.budget.candidates_within(5, ahead)
    assert cap is not None and MIN_CANDIDATES <= cap < FULL_SEARCH
    assert cap * nav.budget.candidate_seconds(5) * LATE_MARGIN <= ahead  # the search fits before the split
    assert ahead <= LATE_MARGIN * max(nav.cfg.planner.search_time, MIN_CANDIDATES * nav.budget.candidate_seconds(5)) + 0.1
    assert nav.budget.candidates_within(1000, nav.budget.mission_ahead(1000)) == MIN_CANDIDATES
    # less time, fewer candidates; never fewer than MIN_CANDIDATES
    caps = [nav.budget.candidates_within(5, s) or FULL_SEARCH for s in (0.1, 1.0, 5.0, 20.0, 60.0)]
    assert caps == sorted(caps) and caps[0] == MIN_CANDIDATES


def test_a_mission_with_lower_bounds_starts_where_the_flight_is_within_them() -> None:
    """A mission at a 3 m/s^2 sent while the flown plan accelerates at ~4: no plan starts from a
    jet beyond its bounds, at any duration (benchmarks/service.py --put saw it refused so); the
    split moves on to where the flown plan's acceleration and jerk are within the mission's."""
    from planner_core import Bounds, Problem, fastest_durations

    fast = Bounds.symmetric(4.0, 4.0, 12.0, 60.0)
    flown = fastest_durations(Problem.from_waypoints([[0.0, 0.0, -2.0], [20.0, 0.0, -2.0]], [1.0], fast))
    assert flown.ok and flown.result.trajectory is not None
    traj = flown.result.trajectory
    nav = _navigator([])
    nav.control.active = traj
    nav.control.jet = lambda t: traj.jet(min(t, traj.t_end))
    nav.control.t = traj.t0
    gentle = Bounds.symmetric(3.0, 3.0, 10.0, 50.0)
    ts = np.linspace(traj.t0, traj.t_end, 400)
    peak = max(float(np.max(np.abs(traj.jet(t)[2]))) for t in ts)
    assert peak > 3.0  # the premise: the flight accelerates beyond the mission's bound
    t_hot = float(ts[int(np.argmax([abs(traj.jet(t)[2][0]) for t in ts]))])
    nav.control.t = t_hot - 0.2
    ahead = nav.ahead_within(gentle, 0.15)
    assert ahead > 0.15
    jet = traj.jet(t_hot - 0.2 + ahead)
    assert np.all(np.abs(jet[2]) <= 3.0 + 1e-9) and np.all(np.abs(jet[3]) <= 10.0 + 1e-9)
    assert nav.ahead_within(fast, 0.15) == 0.15  # within its own bounds: no later split
    # and from there the mission (the companion's default bounds: the gentle ones) plans
    from companion.mission import start_mission
    from companion.obstacles import Known
    from companion.wire.messages import mission_from_message

    cfg = Config()
    spec = mission_from_message({"id": "gentle", "waypoints": [[20.0, 5.0, -2.0], [10.0, 8.0, -2.0]]}, cfg)
    t_split = t_hot - 0.2 + ahead
    assert start_mission(spec, traj.jet(t_split), t_split, Known(), cfg).ok
    assert not start_mission(spec, traj.jet(t_hot), t_hot, Known(), cfg).ok  # where the flight is beyond them
