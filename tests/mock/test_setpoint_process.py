"""Setpoints that a busy service process cannot starve (issue 21.7).

The service runs in this process; the mock autopilot runs in a process of its own (so that what
starves this process does not also stop the autopilot from hearing), with a CPU hog beside both
under normal scheduling. While the vehicle holds in OFFBOARD, a thread of the service's process
keeps the GIL for most of a second at a time, as a long C call does (unpickling a big plan, a
big JSON decode, a sort): here `sorted()` of a list of floats, one C call that never gives the
GIL back.

- With the setpoints from a thread of the service (`[setpoints] process = false`) the stream
  stops for as long as the GIL is held: the autopilot sees a gap over THREAD_STALL and the
  companion reports that it stalled. This shows the hazard is real on this machine.
- With the setpoints from a process of their own (the default) the stream goes on: the gaps the
  autopilot sees stay far below PX4's COM_OF_LOSS_T and nothing stalls.
"""

from __future__ import annotations

import asyncio
import itertools
import os
import random
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from companionkit import Events, service_for, serving, until
from mockkit import free_udp_port

from companion.setpoints import THREAD_STALL
from sitl_mock import read_log

HOG_SECONDS = 0.9  # one GIL hold: over THREAD_STALL (the hold takes longer on a busy machine)
# The event loop is held up as long as the GIL is: past `loop_stall_limit` the loop could not
# supervise the flight, so setpoints are withheld by design. The hold here is about the sender,
# not the loop: a limit above any hold this machine may stretch to.
LOOP_STALL_LIMIT = 30.0
HOGS = 3


class _MockProcess:
    """The mock's `addresses` for companionkit.service_for, served by `python -m sitl_mock`."""

    def __init__(self, port: int) -> None:
        self.addresses = [("127.0.0.1", port)]


@contextmanager
def _processes(tmp_path: Path) -> Iterator[tuple[_MockProcess, Path]]:
    port, log = free_udp_port(), tmp_path / "flight.jsonl"
    mock = subprocess.Popen([sys.executable, "-m", "sitl_mock", "--autopilot", "px4", "--response", "ideal",
                             "--endpoint", f"udpin:127.0.0.1:{port}", "--log", str(log), "--log-rate-hz", "5",
                             "--px4-ready-after", "0"],
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        assert mock.stderr is not None and "sitl_mock" in mock.stderr.readline()
        yield _MockProcess(port), log
    finally:
        for p in (hog, mock):
            p.terminate()
            p.wait(5)


def _sorted_size(seconds: float) -> int:
    """A list length whose sort holds the GIL at least about `seconds` on this machine: sized by
    the fastest of a few sorts (a sort timed while the machine was briefly busier would size the
    hold below THREAD_STALL once it is quieter; a busier machine only makes the hold longer)."""
    n = 300_000
    data = [random.random() for _ in range(n)]
    took = []
    for _ in range(3):
        t = time.perf_counter()
        sorted(data)
        took.append(time.perf_counter() - t)
    return max(n, int(n * seconds / max(min(took), 1e-3)))


def _hold_the_gil(data: list[float]) -> float:
    t = time.perf_counter()
    sorted(data)
    return time.perf_counter() - t


async def _fly_while_starved(tmp_path: Path, process: bool) -> tuple[list[float], list[float], list[dict[str, Any]]]:
    """The GIL holds, the gaps between the setpoints the autopilot heard, the stall events."""
    with _processes(tmp_path) as (mock, log):
        svc = service_for(mock, setpoints={"process": process,  # type: ignore[arg-type]
                                           "loop_stall_limit": LOOP_STALL_LIMIT})
        events = Events(svc)
        async with serving(svc):
            await until(lambda: svc.link.state.has_position, 20, "a position")
            await svc.commands.takeoff(1.0)
            assert svc.flight.airborne
            await asyncio.sleep(1.0)
            data = [random.random() for _ in range(_sorted_size(HOG_SECONDS))]  # sized as the machine is now
            held: list[float] = []
            for k in range(HOGS):
                # the first hold must find the vehicle flown by the stream, or it shows nothing (a
                # stream that already ended has no gap and no stall); say what ended it
                assert k > 0 or svc.control.streaming, (
                    f"the stream had ended before the first hold: state {svc.flight.state.value}, mode "
                    f"{svc.link.state.mode}; events {[(e['type'], e['message']) for e in events.all]}")
                hog = threading.Thread(target=lambda: held.append(_hold_the_gil(data)))
                hog.start()
                while hog.is_alive():
                    await asyncio.sleep(0.01)
                await asyncio.sleep(1.0)
            stalled = events.of("stalled")
        records = read_log(log)
    # every setpoint the autopilot heard, from the first (arming) to the last (the hand-over)
    sent = [r["t"] for r in records if r["type"] == "setpoint" and r.get("valid")]
    gaps = [b - a for a, b in itertools.pairwise(sent)]
    return held, gaps, stalled


@pytest.mark.parametrize("process", [True, False], ids=["process", "thread"])
def test_a_service_holding_the_gil_does_not_starve_the_setpoints(tmp_path: Path, process: bool) -> None:
    held, gaps, stalled = asyncio.run(_fly_while_starved(tmp_path, process))
    assert len(held) == HOGS and min(held) > THREAD_STALL, f"the hog held the GIL only {held}"
    assert max(held) < LOOP_STALL_LIMIT - 1.0, f"the hog held the GIL {held}: the loop's limit is too close"
    assert gaps, "no setpoint reached the autopilot"
    longest = max(gaps)
    print(f"process={process}: GIL held {[round(h, 2) for h in held]} s; longest setpoint gap at the autopilot "
          f"{longest * 1000:.0f} ms; stalled events {len(stalled)}")
    if process:
        # PX4 leaves OFFBOARD after COM_OF_LOSS_T (1 s) without a setpoint; the stream must not
        # come near it, nor near the stall latch (THREAD_STALL) that ends the mission
        assert longest < 0.25, f"setpoints starved for {longest * 1000:.0f} ms"
        assert not stalled, stalled
    else:  # the thread starved, withheld its setpoints and the companion said so
        assert [e for e in stalled if e["stalled"] == "the_setpoint_thread"], stalled
