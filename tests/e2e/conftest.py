"""Shared fixtures for the end-to-end tests (helpers live in e2e_rig.py)."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest
from e2e_rig import Rig


@pytest.fixture(scope="module")
def rig_factory(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Callable[..., Rig]]:
    rigs: list[Rig] = []

    def make(autopilot: str, *mock_args: str) -> Rig:
        rig = Rig(autopilot, tmp_path_factory.mktemp(f"e2e-{autopilot}"), mock_args)
        rigs.append(rig)
        try:
            rig.start()
        except Exception:
            rig.stop()
            raise
        return rig

    yield make
    for rig in rigs:
        rig.stop()
