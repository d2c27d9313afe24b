"""Planner worker processes run at a lower priority than the service (the setpoint loop)."""

from __future__ import annotations

import os

from companion.config import Config
from companion.runtime import PLANNER_NICE, URGENT_NICE, make_planner_pool


def test_planner_processes_are_niced_below_the_service() -> None:
    mine = os.nice(0)
    pools = [(make_planner_pool(Config(), workers=1), PLANNER_NICE),
             (make_planner_pool(Config(), workers=1, nice=URGENT_NICE), URGENT_NICE)]
    try:
        asked = [(pool.submit(os.nice, 0), increment) for pool, increment in pools]  # both start at once
        for future, increment in asked:
            theirs = future.result(timeout=60)
            assert theirs == min(mine + increment, 19)
            assert theirs > mine or mine == 19
    finally:
        for pool, _ in pools:
            pool.shutdown(wait=True)
