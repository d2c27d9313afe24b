"""Realtime scheduling from the service manager is kept for the setpoint thread only."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from companion import rtsched

ROOT = Path(__file__).resolve().parents[2]
CHRT = shutil.which("chrt")
linux_only = pytest.mark.skipif(not hasattr(os, "sched_getscheduler"), reason="Linux scheduling API")


def _fifo_permitted() -> bool:
    if CHRT is None:
        return False
    return subprocess.run([CHRT, "-f", "3", "true"], capture_output=True).returncode == 0


needs_fifo = pytest.mark.skipif(not _fifo_permitted(), reason="SCHED_FIFO not permitted here (CAP_SYS_NICE)")


@linux_only
def test_nothing_is_reserved_under_normal_scheduling() -> None:
    if os.sched_getscheduler(0) != os.SCHED_OTHER:
        pytest.skip("the test runner itself runs under a special policy")
    assert rtsched.reserve() is None
    assert rtsched.starter() is None


@linux_only
def test_a_policy_that_cannot_be_left_stops_the_start(monkeypatch: pytest.MonkeyPatch) -> None:
    """Without sched_setscheduler (a unit filter that forgot it) every thread would run realtime."""
    monkeypatch.setattr(rtsched, "_host", None)
    monkeypatch.setattr(rtsched, "_thread", None)
    monkeypatch.setattr(os, "sched_getscheduler", lambda pid: os.SCHED_FIFO)
    monkeypatch.setattr(os, "sched_getparam", lambda pid: os.sched_param(10))

    def refused(pid: int, policy: int, param: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refused)
    before = threading.active_count()
    with pytest.raises(rtsched.RealtimeError, match="sched_setscheduler"):
        rtsched.reserve()
    assert rtsched.starter() is None
    deadline = time.monotonic() + 5.0
    while threading.active_count() > before and time.monotonic() < deadline:
        time.sleep(0.01)
    assert threading.active_count() == before  # the host thread was released, nothing runs in it


PROBE = textwrap.dedent("""
    import json, os, subprocess, sys, threading
    from companion import rtsched

    def policy():
        p = os.sched_getscheduler(0)
        return {os.SCHED_FIFO: "fifo", os.SCHED_RR: "rr", os.SCHED_OTHER: "other"}.get(p, str(p))

    kept = rtsched.reserve()
    out = {"kept": kept, "main": policy()}
    t = threading.Thread(target=lambda: out.__setitem__("later_thread", policy()))
    t.start(); t.join()
    child = subprocess.run([sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"],
                           capture_output=True, text=True)
    out["child_process"] = int(child.stdout)
    start = rtsched.starter()
    done = threading.Event()
    def body():
        out["reserved"] = policy()
        out["reserved_prio"] = os.sched_getparam(0).sched_priority
        done.set()
    start(body)
    done.wait(10)
    out["second_start"] = rtsched.starter() is None
    print(json.dumps(out))
""")


@linux_only
@needs_fifo
def test_under_fifo_only_the_reserved_thread_keeps_it() -> None:
    assert CHRT is not None
    proc = subprocess.run([CHRT, "-f", "7", sys.executable, "-c", PROBE], capture_output=True, text=True,
                          cwd=ROOT, timeout=60)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["kept"] == "fifo 7"
    assert out["reserved"] == "fifo" and out["reserved_prio"] == 7
    assert out["main"] == "other" and out["later_thread"] == "other"
    assert out["child_process"] == os.SCHED_OTHER
    assert out["second_start"] is True  # one body, once
