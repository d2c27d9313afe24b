"""Session set-up shared by every test directory."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session", autouse=True)
def _compiled_planner_kernel() -> None:
    """Compile the planner's numba kernel once, here, into its on-disk cache: the companion's
    worker processes started by later tests then load it (~0.3 s) instead of each compiling it
    (~20 s) in the middle of a timed flight."""
    from planner_core.iterative import warm_up

    warm_up()
