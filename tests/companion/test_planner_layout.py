"""Where the service plans (companion/runtime.py): missions in one planner process that does not
load numba unless `[planner] compiled` asks, urgent replans in a thread of the service; both
plan verified missions, and the process is handed back its freed heap after each job."""

from __future__ import annotations

import asyncio
import os
import sys
import threading
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from typing import Any

import numpy as np

from companion.config import Config, config_from_dict
from companion.mission import start_mission
from companion.obstacles import Known
from companion.runtime import Runtime, run_and_trim
from companion.wire.messages import mission_from_message
from planner_core import rest_jet
from planner_core.window import aot_ready, aot_unavailable, kernel_kind


def plan_probe(cfg: Config) -> dict[str, Any]:
    """A mission planned where the runtime put us, and what that place holds."""
    spec = mission_from_message({"id": "probe", "waypoints": [[2.0, 0.0, -1.5], [2.0, 2.0, -1.5],
                                                              [0.0, 2.0, -1.5], [0.0, 0.0, -1.5]]}, cfg)
    out = start_mission(spec, rest_jet(np.array([0.0, 0.0, -1.5])), 0.0, Known(), cfg)
    assert out.route is not None
    return {"ok": out.ok, "pid": os.getpid(), "thread": threading.current_thread().name,
            "numba": "numba" in sys.modules, "compiled_steps": out.route.trajectory.stats.get("n_compiled_steps"),
            "kernel": kernel_kind() if out.route.trajectory.stats.get("n_compiled_steps") else None}


async def _both(rt: Runtime, cfg: Config) -> tuple[dict[str, Any], dict[str, Any]]:
    rt.loop = asyncio.get_running_loop()
    try:
        return await rt.plan(plan_probe, cfg), await rt.plan(plan_probe, cfg, urgent=True)
    finally:
        rt.shutdown()


def test_default_layout_one_light_planner_process_and_an_urgent_thread() -> None:
    cfg = Config()
    rt = Runtime(cfg)
    assert isinstance(rt.pool, ProcessPoolExecutor) and isinstance(rt.urgent_pool, ThreadPoolExecutor)
    mission, urgent = asyncio.run(_both(rt, cfg))
    assert mission["ok"] and urgent["ok"]
    assert mission["pid"] != os.getpid() and not mission["numba"]
    # the compiled pass's AOT build where `make setup` built it (no numba), else the numpy path
    assert (mission["compiled_steps"] > 0) == (aot_ready() and mission["kernel"] == "aot")
    assert urgent["pid"] == os.getpid() and urgent["thread"].startswith("urgent")


def test_the_setup_built_the_kernel_the_service_plans_with() -> None:
    """`make setup` (which `make test` runs) builds the AOT kernel on this machine: without it the
    service plans ~10x slower and says so at start-up; a test run without it would not notice."""
    assert aot_ready(), aot_unavailable()


def test_compiled_planner_processes_on_request() -> None:
    cfg = config_from_dict({"planner": {"compiled": True, "urgent": "process"}})
    rt = Runtime(cfg)
    assert isinstance(rt.urgent_pool, ProcessPoolExecutor)
    mission, urgent = asyncio.run(_both(rt, cfg))
    assert mission["ok"] and urgent["ok"] and urgent["pid"] != os.getpid()
    # the compiled pass: its AOT build where `make setup` built it (no numba), else numba's JIT
    assert mission["compiled_steps"] > 0 and mission["kernel"] in ("aot", "jit")
    assert mission["numba"] == (mission["kernel"] == "jit")


def test_run_and_trim_returns_the_result_and_raises_what_failed() -> None:
    assert run_and_trim(sum, [1, 2, 3]) == 6
    # the heap is trimmed after the answer has gone, not before (a full collection: ~23 ms)
    from companion import runtime

    timer = runtime._trim_timer[0]
    assert timer.is_alive()
    timer.join(runtime.TRIM_DELAY + 2.0)
    assert not timer.is_alive()
    assert run_and_trim(sum, [1]) == 1 and run_and_trim(sum, [2]) == 2
    assert len(runtime._trim_timer) == 1  # back-to-back jobs: one trim, after the last
    try:
        run_and_trim(int, "not a number")
    except ValueError:
        pass
    else:
        raise AssertionError("the job's exception was swallowed")


_ORPHAN_PARENT = """
import os, sys, time
from companion.config import Config
from companion.runtime import make_planner_pool
pool = make_planner_pool(Config())
print(pool.submit(os.getpid).result(), flush=True)
time.sleep(60)
"""


def test_planner_process_leaves_when_the_service_dies() -> None:
    """A service killed outright (SIGKILL, a watchdog abort) must not leave its planner process
    behind holding memory: the worker notices it was re-parented and exits."""
    import signal
    import subprocess
    import time

    parent = subprocess.Popen([sys.executable, "-c", _ORPHAN_PARENT], stdout=subprocess.PIPE, text=True)
    try:
        assert parent.stdout is not None
        worker = int(parent.stdout.readline())
        os.kill(worker, 0)  # alive while its service is
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=10)
        deadline = time.monotonic() + 15.0
        while time.monotonic() < deadline:
            try:
                os.kill(worker, 0)
            except ProcessLookupError:
                break
            time.sleep(0.1)
        else:
            os.kill(worker, signal.SIGKILL)
            raise AssertionError(f"planner process {worker} outlived its killed service")
    finally:
        if parent.poll() is None:
            parent.kill()
