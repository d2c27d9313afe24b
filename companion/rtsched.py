"""Realtime scheduling granted by the service manager, kept for the setpoint thread only.

systemd's `CPUSchedulingPolicy=fifo` starts the service's main thread under SCHED_FIFO
without giving the service any capability: the unit keeps an empty capability set and
`RestrictRealtime=yes`, so the service can keep or give up that policy but never acquire
it. Only the setpoint thread should keep it (a sample and a send a tick: 1-3 % of a core);
the event loop, Zenoh's and the planner's threads and the planner processes must run
normally, or a long plan would starve the computer.

Threads inherit the policy of the thread that creates them. So `reserve()`, called by
`python -m companion run` before anything else starts a thread, starts a host thread while
the main thread still has the policy, then returns the main thread to SCHED_OTHER (at its
nice value): every thread and process created afterwards runs normally. The service later
runs its setpoint thread's body in that host (`starter()`).
"""

from __future__ import annotations

import os
import queue
import threading
from collections.abc import Callable

_host: queue.SimpleQueue[Callable[[], None]] | None = None
_thread: threading.Thread | None = None


class RealtimeError(RuntimeError):
    pass


def _policy_name(policy: int) -> str | None:
    names = {getattr(os, "SCHED_FIFO", -1): "fifo", getattr(os, "SCHED_RR", -1): "rr"}
    return names.get(policy)


def reserve() -> str | None:
    """If this (main) thread runs under SCHED_FIFO/RR: keep that policy for one host thread
    and leave it here. Returns e.g. "fifo 10", or None when there was nothing to keep.
    Raises RealtimeError when the policy cannot be left (the unit must allow
    sched_setscheduler): running everything under it would be worse than not starting."""
    global _host, _thread
    if _thread is not None or not hasattr(os, "sched_getscheduler"):
        return None
    policy = os.sched_getscheduler(0)
    name = _policy_name(policy)
    if name is None:
        return None
    described = f"{name} {os.sched_getparam(0).sched_priority}"
    host: queue.SimpleQueue[Callable[[], None]] = queue.SimpleQueue()
    thread = threading.Thread(target=lambda: host.get()(), name="setpoints", daemon=True)
    thread.start()
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except OSError as exc:
        host.put(lambda: None)  # release the host: nothing may run under the policy
        raise RealtimeError(
            f"started under SCHED_{name.upper()} but cannot return the main thread to normal "
            f"scheduling ({exc}): every thread and planner process would run realtime. "
            "Allow sched_setscheduler (systemd: SystemCallFilter=sched_setscheduler) or start "
            "without CPUSchedulingPolicy=") from None
    _host, _thread = host, thread
    return described


def starter() -> Callable[[Callable[[], None]], threading.Thread] | None:
    """A function that runs a body in the reserved thread (once), or None if none is reserved."""
    if _host is None or _thread is None:
        return None

    def start(body: Callable[[], None]) -> threading.Thread:
        global _host
        host, thread = _host, _thread
        if host is None or thread is None:
            raise RealtimeError("the reserved realtime thread is already in use")
        _host = None
        host.put(body)
        return thread

    return start
