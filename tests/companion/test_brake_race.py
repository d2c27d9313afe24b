"""The braking race: `Brakes` owns it; `StopGuard` is its data and never calls back into it."""

from __future__ import annotations

import ast
import asyncio
import inspect
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

import companion.braking as braking
from companion.braking import Brakes, Replanned, StopContext, StopGuard, StopPlan
from companion.config import Config
from companion.flight import FlightState, State
from companion.report import Reporter
from companion.supervisor import Supervisor
from companion.wire.messages import bounds_from
from planner_core import hold


def test_the_guard_names_no_brakes() -> None:
    tree = ast.parse(inspect.getsource(StopGuard))
    names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} | \
        {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
    assert not {"Brakes", "brakes", "stop_future"} & names
    assert list(inspect.signature(StopGuard).parameters) == ["base", "hit"]


def _brakes(pool: ThreadPoolExecutor) -> tuple[Brakes, Any]:
    cfg = Config()
    base = hold(np.array([0.0, 0.0, -1.5]), 0.0)
    control = SimpleNamespace(committed=lambda: 0.0, now=lambda: 0.0, clock=lambda: (lambda: 0.0), active=base)
    runtime = SimpleNamespace(loop=asyncio.get_running_loop(), brake_pool=pool)
    flight = Supervisor(FlightState(State.STREAMING, airborne=True))
    ctx = StopContext(None, (), bounds_from(None, cfg))
    brakes = Brakes(cfg, flight, control, runtime, Reporter(flight), lambda: ctx,  # type: ignore[arg-type]
                    lambda: np.zeros(3))
    return brakes, base


@pytest.mark.parametrize("asked", [False, True])
def test_a_stop_asked_for_is_planned_at_once_else_just_before_the_deadline(asked: bool,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    planned: list[float] = []

    def fake_plan_stop(base: Any, starts: list[float], *_: Any) -> StopPlan:
        planned.append(starts[0])
        return StopPlan(None, starts[0], "planned", True)

    monkeypatch.setattr(braking, "plan_stop", fake_plan_stop)

    async def run() -> StopGuard:
        with ThreadPoolExecutor(1) as pool:
            brakes, base = _brakes(pool)
            guard = StopGuard(base, hit=100.0)
            guard.bring_forward(90.0, 100.0)  # far ahead: the race would prepare at 90 - BRAKE_PREPARE
            replan: asyncio.Future[Replanned] = asyncio.get_running_loop().create_future()
            race = asyncio.create_task(brakes.race(guard, replan, [], 0.0, "test"))  # type: ignore[arg-type]
            await asyncio.sleep(0.01)
            assert guard.future is None and not planned
            if asked:
                guard.prepare()  # as the replan does when the local replan fails
            for _ in range(50):
                await asyncio.sleep(0.002)
            replan.set_result(Replanned(True))
            await asyncio.wait_for(race, 2.0)
            return guard

    guard = asyncio.run(run())
    assert planned == ([90.0] if asked else [])
    assert (guard.future is not None) == asked
