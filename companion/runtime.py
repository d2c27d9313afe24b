"""Where work runs: executors and their priorities, garbage collection paced by the setpoints,
and logging kept off the loop.

Long mission plans go to one planner process (low priority); replans and stops never queue
behind them: an urgent thread for full replans (the fallback after a failed local replan), a
thread for local replans (a few ms: pickling to a process would cost more), two threads for
stops, one each for encoding and decoding.

Footprint (benchmarks/footprint.py): numba and LLVM cost ~105 MB resident in each process that
loads the compiled pass's JIT build, so by default no process of the service loads them
(`[planner] compiled`); every process uses the compiled pass's ahead-of-time build instead
(`planner_core.build_kernel`, built by `make setup`: <1 MB, ~ms to load, the same plans), and
the numpy path where that is not built (~10x slower a window step: a 1000-waypoint mission
~3-5 s instead of a few hundred ms). A mission plan in a thread of the service (no
second interpreter: ~65 MB less) holds the GIL for most of a second and stalls the setpoints
and the pop-up replans (measured: jitter p99 8 ms, pop-up 75 ms), so missions go to a process;
the urgent replans are rare and short, and a thread of their own spares a second process.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import gc
import logging
import logging.handlers
import math
import multiprocessing
import os
import queue
import signal
import threading
import time
from collections.abc import Callable
from concurrent.futures import BrokenExecutor, Executor, ProcessPoolExecutor, ThreadPoolExecutor
from typing import Any

from companion.config import Config
from companion.tap import NO_TAP, Tap

# Nice increments (relative to the service's own, e.g. systemd's Nice=-5) of the planner
# processes: mission planning yields the CPU to the service's process on a busy computer;
# the urgent worker (replans, the fallback after a failed local replan) less so, as it races a
# braking deadline, but still behind the loop.
PLANNER_NICE = 10
URGENT_NICE = 3


def background_priority(increment: int, compiled: bool = False) -> None:
    """A planner process: lower priority, no KeyboardInterrupt traceback of its own when the
    operator presses Ctrl-C (the service shuts it down), and the compiled pass only if asked."""
    with contextlib.suppress(OSError):
        os.nice(increment)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _exit_with_parent(os.getppid())
    if not compiled:
        from planner_core.window import kernel_build

        kernel_build("aot")  # no numba: its AOT build (ms to load, <1 MB) where built, else the numpy path


def _exit_with_parent(parent: int, period: float = 0.5) -> None:
    """A planner process whose service died (SIGKILL, a crash, a watchdog abort) would wait on
    its call queue forever and hold its memory: it leaves as soon as it is re-parented."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(period)
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def trim_heap() -> None:
    """Hand the heap a big plan freed back to the system: glibc keeps it for reuse (~70 MB
    after a 1000-waypoint plan), and an idle planner process should be small. A no-op off glibc."""
    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None).malloc_trim(0)


def return_heap() -> None:
    """glibc's free heap pages back to the system, without a collection (the service's
    collections are paced by the setpoints: GcPacer). ctypes releases the GIL for the call."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None).malloc_trim(0)


TRIM_DELAY = 0.2  # s after a job: the planner process's heap is trimmed then, unless another job came

_trim_timer: list[threading.Timer] = []


def trim_soon(delay: float = TRIM_DELAY) -> None:
    """`trim_heap` `delay` s from now in a thread of this process (a later call moves it)."""
    for t in _trim_timer:
        t.cancel()
    timer = threading.Timer(delay, trim_heap)
    timer.daemon = True
    timer.start()
    _trim_timer[:] = [timer]


def run_and_trim(fn: Callable[..., Any], *args: Any) -> Any:
    """fn(*args) in a planner process; its heap trimmed just after the answer has gone: the full
    collection takes ~23 ms after a small plan, which delayed every answer by as much (a
    5-waypoint mission in flight: 54 ms from arrival to the first setpoint, 20 ms of it planning)."""
    try:
        return fn(*args)
    finally:
        trim_soon()


def make_planner_pool(cfg: Config, workers: int | None = None, nice: int = PLANNER_NICE) -> Executor:
    n = cfg.planner.workers if workers is None else workers
    if cfg.planner.executor == "process":
        return ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=background_priority, initargs=(nice, cfg.planner.compiled))
    # Threads keep normal priority: a low-priority thread holding the GIL would hold it longer.
    return ThreadPoolExecutor(n, thread_name_prefix="planner")


def make_urgent_pool(cfg: Config) -> Executor:
    """Full replans that race a braking deadline: never behind a mission plan."""
    if cfg.planner.urgent == "process":
        return make_planner_pool(cfg, workers=1, nice=URGENT_NICE)
    return ThreadPoolExecutor(1, thread_name_prefix="urgent")


class Runtime:
    """The service's executors; `on_planner_died` is told when a planner process died."""

    def __init__(self, cfg: Config, on_planner_died: Callable[[], None] = lambda: None) -> None:
        self.cfg = cfg
        self.on_planner_died = on_planner_died
        self.pool: Executor = make_planner_pool(cfg)
        self.urgent_pool: Executor = make_urgent_pool(cfg)
        self.replan_pool = ThreadPoolExecutor(1, thread_name_prefix="replan")
        self.io_pool = ThreadPoolExecutor(1, thread_name_prefix="encode")
        self.decode_pool = ThreadPoolExecutor(1, thread_name_prefix="decode")
        # Stops are planned here, never behind a replan (in the urgent process) that may be
        # what is late: two threads, so a fresh stop need not wait for a prepared one.
        self.brake_pool = ThreadPoolExecutor(2, thread_name_prefix="brake")
        self.loop: asyncio.AbstractEventLoop | None = None
        self.tap: Tap = NO_TAP  # every planner call, recorded (companion/recorder.py)

    def pools(self) -> tuple[Executor, ...]:
        return (self.pool, self.urgent_pool, self.replan_pool, self.io_pool, self.decode_pool, self.brake_pool)

    async def plan(self, fn: Any, *args: Any, urgent: bool = False) -> Any:
        """fn(*args) in a planner process or thread (a process is restarted if it died: this
        request then fails)."""
        assert self.loop is not None
        pool = self.urgent_pool if urgent else self.pool
        where = "process" if isinstance(pool, ProcessPoolExecutor) else "thread"
        call, call_args = (run_and_trim, (fn, *args)) if where == "process" else (fn, args)
        try:
            return await self._recorded(pool, where, fn, args, call, call_args)
        except BrokenExecutor:
            if urgent:
                self.urgent_pool = make_urgent_pool(self.cfg)
            else:
                self.pool = make_planner_pool(self.cfg)
            self.on_planner_died()
            raise

    async def run(self, pool: Executor, fn: Any, *args: Any) -> Any:
        assert self.loop is not None
        return await self._recorded(pool, "thread", fn, args, fn, args)

    async def _recorded(self, pool: Executor, where: str, fn: Any, args: tuple[Any, ...], call: Any,
                        call_args: tuple[Any, ...]) -> Any:
        """call(*call_args) in pool; the tap is told fn, args and what came back."""
        assert self.loop is not None
        submitted = time.monotonic()
        try:
            result = await self.loop.run_in_executor(pool, call, *call_args)
        except Exception as exc:
            self.tap.plan(fn, args, exc, submitted, time.monotonic(), where)
            raise
        self.tap.plan(fn, args, result, submitted, time.monotonic(), where)
        return result

    def shutdown(self) -> None:
        for pool in self.pools():
            pool.shutdown(wait=False, cancel_futures=True)


class GcPacer:
    """Garbage collection at the setpoint thread's pace.

    CPython's automatic collection starts in whichever thread allocates past a threshold and
    holds the GIL for the whole pass, so a pass over a big heap (a decoded 1000-waypoint
    mission, its route) can land in the middle of a tick. `start()` freezes the start-up heap
    (never scanned again) and turns automatic collection off; the loop then calls `after_send`
    right after each setpoint, when the next deadline is furthest away: a young collection once
    enough objects have piled up, an older one every few of those, a full one every
    `full_every` seconds, each only with `slack` seconds left before the next deadline.
    """

    def __init__(self, young: int = 2000, full_every: float = 5.0, slack: float = 0.008,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        self.young = young
        self.full_every = full_every
        self.slack = slack
        self.clock = clock
        self.enabled = False
        self.last_full = -math.inf
        self.worst = 0.0  # longest collection so far (s)
        self.collections = [0, 0, 0]
        self.last: tuple[int, float] | None = None  # (generation, seconds) of the latest collection

    def start(self, now: float) -> None:
        gc.collect()
        gc.freeze()
        gc.disable()
        self.enabled = True
        self.last_full = now

    def stop(self) -> None:
        if self.enabled:
            self.enabled = False
            gc.enable()

    def due(self, now: float) -> int | None:
        """The generation to collect now, or None."""
        if now - self.last_full >= self.full_every:
            return 2
        young, older, _ = gc.get_count()
        if young < self.young:
            return None
        return 1 if older >= 10 else 0

    def after_send(self, now: float, next_deadline: float) -> None:
        if not self.enabled or next_deadline - now < self.slack:
            return
        gen = self.due(now)
        if gen is None:
            return
        t0 = self.clock()
        gc.collect(gen)
        took = self.clock() - t0
        self.worst = max(self.worst, took)
        self.last = (gen, took)
        self.collections[gen] += 1
        if gen == 2:
            self.last_full = now


def log_off_loop() -> logging.handlers.QueueListener | None:
    """Route the root logger's handlers through a queue served by a listener thread: a log call
    on the loop then only formats and enqueues, it never waits on a write."""
    root = logging.getLogger()
    handlers = [h for h in root.handlers if not isinstance(h, logging.handlers.QueueHandler)]
    if not handlers:
        return None
    q: queue.SimpleQueue[logging.LogRecord] = queue.SimpleQueue()
    listener = logging.handlers.QueueListener(q, *handlers, respect_handler_level=True)
    for h in handlers:
        root.removeHandler(h)
    root.addHandler(logging.handlers.QueueHandler(q))
    listener.start()
    return listener


def restore_logging(listener: logging.handlers.QueueListener | None) -> None:
    if listener is None:
        return
    root = logging.getLogger()
    for qh in [h for h in root.handlers if isinstance(h, logging.handlers.QueueHandler)]:
        root.removeHandler(qh)
    listener.stop()  # writes out what is still queued
    for h in listener.handlers:
        root.addHandler(h)
