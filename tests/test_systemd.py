"""The systemd unit: it verifies, it is well hardened, and the hardening does not break the service.

systemd is not PID 1 here, so the runtime checks emulate the two restrictions most likely to
break a Python/numpy/Rust stack: RestrictAddressFamilies= (in the unit) and
MemoryDenyWriteExecute= (left to a site drop-in: numba's JIT needs it off) are re-created with
the same seccomp rules systemd installs, and the syscalls the workload makes (traced with
strace) are checked against the unit's SystemCallFilter= allow-list.
"""

from __future__ import annotations

import configparser
import contextlib
import itertools
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest

from companion.sdnotify import Notifier, watchdog_interval

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "systemd" / "bezier-companion@.service"
SERIAL_DROPIN = ROOT / "systemd" / "serial.conf"
INSTALLED_PYTHON = "/opt/bezier-companion/venv/bin/python"
ANALYZE = shutil.which("systemd-analyze")
STRACE = shutil.which("strace")
MAX_EXPOSURE = 2.0

needs_analyze = pytest.mark.skipif(ANALYZE is None, reason="systemd-analyze not installed")


def _unit_for_host(tmp_path: Path, extra: str = "") -> Path:
    """The unit as an instance, with ExecStart on this machine's interpreter (verify checks it)."""
    text = UNIT.read_text().replace(INSTALLED_PYTHON, sys.executable)
    path = tmp_path / "bezier-companion@uav1.service"
    path.write_text(text + ("\n" + extra if extra else ""))
    return path


def _directives(text: str) -> dict[str, list[str]]:
    values: dict[str, list[str]] = {}
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";", "[")):
            continue
        key, _, value = line.partition("=")
        values.setdefault(key.strip(), []).append(value.strip())
    return values


def test_unit_is_notify_with_watchdog_and_restart() -> None:
    d = _directives(UNIT.read_text())
    assert d["Type"] == ["notify"]
    watchdog = d["WatchdogSec"][-1]
    assert re.fullmatch(r"\d+(\.\d+)?s?", watchdog) and 0 < float(watchdog.rstrip("s")) <= 5
    assert d["Restart"] == ["on-failure"]
    assert d["ExecStart"] == [
        f"{INSTALLED_PYTHON} -m companion run --config /etc/bezier-companion/%i.toml"
    ]
    assert d["DynamicUser"] == ["yes"]
    assert d["CapabilityBoundingSet"] == [""]
    # numba's JIT needs executable memory: W^X is left to a site drop-in (the planner degrades)
    assert "MemoryDenyWriteExecute" not in d
    assert d["CacheDirectory"] == ["bezier-companion/%i"]
    assert "NUMBA_CACHE_DIR=%C/bezier-companion/%i" in d["Environment"]


def test_serial_dropin_is_a_plain_service_section() -> None:
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    parser.read_string(SERIAL_DROPIN.read_text())
    assert parser.sections() == ["Service"]
    d = _directives(SERIAL_DROPIN.read_text())
    assert d["PrivateDevices"] == ["no"]
    assert {"char-ttyACM rw", "char-ttyS rw"} <= set(d["DeviceAllow"])
    assert d["SupplementaryGroups"] == ["dialout"]


@needs_analyze
@pytest.mark.parametrize("dropin", ["", "serial"])
def test_unit_verifies(tmp_path: Path, dropin: str) -> None:
    assert ANALYZE is not None
    unit = _unit_for_host(tmp_path, SERIAL_DROPIN.read_text() if dropin else "")
    proc = subprocess.run(
        [ANALYZE, "verify", str(unit)], capture_output=True, text=True, timeout=60
    )
    ours = [line for line in proc.stderr.splitlines() if unit.name in line]
    assert proc.returncode == 0 and not ours, proc.stderr


def test_verify_would_catch_a_broken_unit(tmp_path: Path) -> None:
    if ANALYZE is None:
        pytest.skip("systemd-analyze not installed")
    unit = _unit_for_host(tmp_path)
    unit.write_text(unit.read_text().replace(sys.executable, str(tmp_path / "missing-python")))
    proc = subprocess.run([ANALYZE, "verify", str(unit)], capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 or "missing-python" in proc.stderr


def _exposure(unit: Path) -> float:
    assert ANALYZE is not None
    proc = subprocess.run(
        [ANALYZE, "security", "--offline=yes", "--no-pager", str(unit)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    match = re.search(r"Overall exposure level for \S+: (\d+(?:\.\d+)?)", proc.stdout)
    assert match, proc.stdout + proc.stderr
    return float(match.group(1))


@needs_analyze
@pytest.mark.parametrize("dropin", ["", "serial"])
def test_security_exposure_is_low(tmp_path: Path, dropin: str) -> None:
    unit = _unit_for_host(tmp_path, SERIAL_DROPIN.read_text() if dropin else "")
    assert _exposure(unit) <= MAX_EXPOSURE


@needs_analyze
def test_exposure_parser_sees_a_weak_unit(tmp_path: Path) -> None:
    weak = tmp_path / "weak.service"
    weak.write_text(f"[Service]\nExecStart={sys.executable} -c pass\n")
    assert _exposure(weak) > MAX_EXPOSURE


# --- runtime emulation of the sandbox ---------------------------------------------------------

# seccomp rules equivalent to systemd's MemoryDenyWriteExecute=yes, to
# RestrictAddressFamilies=AF_INET AF_INET6 AF_UNIX AF_NETLINK and to RestrictRealtime=yes
# (systemd's src/shared/seccomp-util.c).
SANDBOX = textwrap.dedent(
    r'''
    import ctypes, errno, os, platform, socket, struct, sys

    ARCHES = {  # audit arch, mmap, mprotect, pkey_mprotect, shmat, socket, sched_setscheduler
        "x86_64": (0xC000003E, 9, 10, 329, 30, 41, 144),
        "aarch64": (0xC00000B7, 222, 226, 288, 196, 198, 119),
    }
    SCHED_OTHER, SCHED_BATCH, SCHED_IDLE = 0, 3, 5
    ALLOWED_FAMILIES = (socket.AF_UNIX, socket.AF_INET, socket.AF_INET6, socket.AF_NETLINK)
    PROT_WRITE, PROT_EXEC, SHM_EXEC = 0x2, 0x4, 0o100000
    RET_ALLOW = 0x7FFF0000

    def errno_ret(e):
        return 0x00050000 | e

    def program():
        arch, mmap_nr, mprotect_nr, pkey_nr, shmat_nr, socket_nr, sched_nr = ARCHES[platform.machine()]
        wx = os.environ.get("EMULATE_MDWE", "1") == "1"
        rt = os.environ.get("EMULATE_RESTRICT_REALTIME", "0") == "1"
        arg = lambda i: 16 + 8 * i  # low 32 bits of seccomp_data.args[i] (little endian)
        ops = [  # (code, k, jump-if-true label, jump-if-false label); None = next instruction
            ("ld", 4, None, None), ("jeq", arch, None, "allow"),
            ("ld", 0, None, None),
            ("jeq", mmap_nr, "mmap" if wx else "allow", None),
            ("jeq", mprotect_nr, "exec" if wx else "allow", None),
            ("jeq", pkey_nr, "exec" if wx else "allow", None), ("jeq", shmat_nr, "shm" if wx else "allow", None),
            ("jeq", socket_nr, "sock", None), ("jeq", sched_nr, "sched" if rt else "allow", None),
            ("ret", RET_ALLOW, None, None),
            ("mmap:ld", arg(2), None, None), ("and", PROT_WRITE | PROT_EXEC, None, None),
            ("jeq", PROT_WRITE | PROT_EXEC, "eperm", "allow"),
            ("exec:ld", arg(2), None, None), ("jset", PROT_EXEC, "eperm", "allow"),
            ("shm:ld", arg(2), None, None), ("jset", SHM_EXEC, "eperm", "allow"),
            # RestrictRealtime=: only the normal policies may be set (so one can leave a realtime
            # policy set by the service manager, never acquire one)
            ("sched:ld", arg(1), None, None), ("jeq", SCHED_OTHER, "allow", None),
            ("jeq", SCHED_BATCH, "allow", None), ("jeq", SCHED_IDLE, "allow", "eperm"),
            ("sock:ld", arg(0), None, None),
        ] + [("jeq", f, "allow", None) for f in ALLOWED_FAMILIES] + [
            ("ret", errno_ret(errno.EAFNOSUPPORT), None, None),
            ("eperm:ret", errno_ret(errno.EPERM), None, None),
            ("allow:ret", RET_ALLOW, None, None),
        ]
        labels = {}
        for i, op in enumerate(ops):
            if ":" in op[0]:
                labels[op[0].split(":")[0]] = i
        codes = {"ld": 0x20, "jeq": 0x15, "jset": 0x45, "and": 0x54, "ret": 0x06}
        out = b""
        for i, (name, k, jt, jf) in enumerate(ops):
            code = codes[name.split(":")[-1]]
            rel = lambda label: 0 if label is None else labels[label] - i - 1
            out += struct.pack("HBBI", code, rel(jt), rel(jf), k)
        return out, len(ops)

    def install():
        libc = ctypes.CDLL(None, use_errno=True)
        filt, n = program()
        buf = ctypes.create_string_buffer(filt)
        class Prog(ctypes.Structure):
            _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]
        prog = Prog(n, ctypes.addressof(buf))
        if libc.prctl(38, 1, 0, 0, 0) != 0:  # PR_SET_NO_NEW_PRIVS, as NoNewPrivileges=yes
            raise OSError(ctypes.get_errno(), "PR_SET_NO_NEW_PRIVS")
        if libc.prctl(22, 2, ctypes.byref(prog), 0, 0) != 0:  # PR_SET_SECCOMP, MODE_FILTER
            raise OSError(ctypes.get_errno(), "PR_SET_SECCOMP")

    install()
    os.execv(sys.executable, [sys.executable, *sys.argv[1:]])
    '''
)

# Exercises what the service loads at run time: the numeric stack and both QP solvers, the
# planner when it is present, Zenoh (listening on all interfaces, which enumerates them over
# netlink), and a MAVLink UDP link. It also proves the emulated sandbox is in force.
WORKLOAD = textwrap.dedent(
    r'''
    import ctypes, errno, json, mmap, socket, sys, time
    import numpy as np
    import daqp, osqp, scipy.sparse as sp
    import zenoh
    from pymavlink import mavutil

    report = {}
    libc = ctypes.CDLL(None, use_errno=True)
    libc.mmap.restype = ctypes.c_void_p
    libc.mmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int,
                          ctypes.c_int, ctypes.c_long]
    wx = libc.mmap(None, 4096, 0x1 | 0x2 | 0x4, 0x2 | 0x20, -1, 0)  # RWX, private anonymous
    report["wx_mmap_errno"] = ctypes.get_errno() if wx in (None, ctypes.c_void_p(-1).value) else 0
    try:
        socket.socket(socket.AF_PACKET, socket.SOCK_DGRAM)
        report["packet_socket"] = "allowed"
    except OSError as exc:
        report["packet_socket"] = errno.errorcode.get(exc.errno, str(exc.errno))

    rng = np.random.default_rng(0)
    a = rng.standard_normal((40, 12))
    h = a.T @ a + np.eye(12)
    x, _, flag, _ = daqp.solve(h, rng.standard_normal(12), np.eye(12), np.ones(12), -np.ones(12))
    report["daqp_flag"] = int(flag)
    solver = osqp.OSQP()
    solver.setup(sp.csc_matrix(h), rng.standard_normal(12), sp.csc_matrix(np.eye(12)),
                 -np.ones(12), np.ones(12), verbose=False)
    report["osqp_status"] = str(solver.solve().info.status)
    try:
        import planner_core.bezier  # noqa: F401  (numeric core used by the service)
        report["planner_core"] = "imported"
        from planner_core import Bounds, IterativeOptions, Problem
        from planner_core.iterative import plan_iterative
        wps = np.array([[0, 0, 0], [2, 1, 0], [4, 0, 1], [6, 2, 1], [8, 0, 0]], dtype=float)
        problem = Problem.from_waypoints(wps, np.full(4, 2.0), Bounds.symmetric(7, 6.5, 15, 60))
        res = plan_iterative(problem, IterativeOptions(window=2))
        report["plan_ok"] = res.ok
        report["compiled_steps"] = res.stats["n_compiled_steps"]
        report["compiled_unavailable"] = res.stats["compiled_unavailable"]
    except ImportError as exc:
        report["planner_core"] = f"missing: {exc}"

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("listen/endpoints", json.dumps(["tcp/0.0.0.0:0"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    got = []
    with zenoh.open(conf) as session:
        sub = session.declare_subscriber("bezier/test/echo", lambda s: got.append(bytes(s.payload)))
        time.sleep(0.2)
        session.put("bezier/test/echo", b"ping")
        deadline = time.monotonic() + 3
        while not got and time.monotonic() < deadline:
            time.sleep(0.02)
        sub.undeclare()
    report["zenoh_echo"] = got[:1] == [b"ping"]

    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(3)
    link = mavutil.mavlink_connection(f"udpout:127.0.0.1:{rx.getsockname()[1]}",
                                      source_system=1, source_component=191)
    link.mav.heartbeat_send(18, 8, 0, 0, 0)
    report["mavlink_bytes"] = len(rx.recv(1024))
    print("REPORT " + json.dumps(report), flush=True)
    '''
)


def _unit_environment() -> dict[str, str]:
    pairs = (v.partition("=") for v in _directives(UNIT.read_text()).get("Environment", []))
    # values with systemd specifiers (%C, %i) name directories that exist only under systemd;
    # here numba uses its in-tree cache, compiled by the test session's warm-up
    return {k: v for k, _, v in pairs if "%" not in v}


def _run_sandboxed(tmp_path: Path, prefix: list[str], mdwe: bool = False,
                   extra_env: dict[str, str] | None = None) -> tuple[dict[str, Any], str]:
    sandbox = tmp_path / "sandbox.py"
    workload = tmp_path / "workload.py"
    sandbox.write_text(SANDBOX)
    workload.write_text(WORKLOAD)
    env = dict(os.environ)
    env.update(_unit_environment())
    env.update(extra_env or {})
    env["EMULATE_MDWE"] = "1" if mdwe else "0"
    proc = subprocess.run(
        [*prefix, sys.executable, str(sandbox), str(workload)],
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
        cwd=ROOT,
    )
    line = next((x for x in proc.stdout.splitlines() if x.startswith("REPORT ")), None)
    assert proc.returncode == 0 and line, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads(line[len("REPORT ") :]), proc.stderr


@pytest.mark.skipif(sys.platform != "linux", reason="seccomp is Linux-only")
def test_service_stack_runs_under_the_address_family_restriction(tmp_path: Path) -> None:
    report, _ = _run_sandboxed(tmp_path, [])
    # The emulation is in force: packet sockets are refused (W+X memory is allowed, as in the unit)...
    assert report["packet_socket"] == "EAFNOSUPPORT"
    assert report["wx_mmap_errno"] == 0
    # ...and still the solvers, the compiled planner, Zenoh and MAVLink all work.
    assert report["daqp_flag"] == 1
    assert report["osqp_status"].lower() == "solved"
    assert report["plan_ok"] is True and report["compiled_unavailable"] is None
    assert report["compiled_steps"] == 3
    assert report["zenoh_echo"] is True
    assert report["mavlink_bytes"] > 0


@pytest.mark.skipif(sys.platform != "linux", reason="seccomp is Linux-only")
def test_service_stack_under_a_wx_policy_plans_without_the_jit(tmp_path: Path) -> None:
    """A site drop-in with MemoryDenyWriteExecute=yes: numba cannot start, the planner says so
    and plans on the numpy + daqp path; nothing else in the stack notices. The compiled pass's
    AOT build (planner_core.build_kernel), a plain shared library, needs no W+X memory: where it
    is built, the planner uses it under the policy."""
    report, _ = _run_sandboxed(tmp_path, [], mdwe=True, extra_env={"PLANNER_CORE_KERNEL": "jit"})
    assert report["wx_mmap_errno"] == 1  # EPERM
    assert report["plan_ok"] is True and report["compiled_steps"] == 0
    assert "executable memory" in report["compiled_unavailable"]
    assert report["daqp_flag"] == 1
    assert report["zenoh_echo"] is True
    assert report["mavlink_bytes"] > 0
    from planner_core import kernel_aot

    if isinstance(kernel_aot.load(), str):
        return  # no (fresh) AOT build here: test_kernel_aot.py says why
    report, _ = _run_sandboxed(tmp_path, [], mdwe=True, extra_env={"PLANNER_CORE_KERNEL": "aot"})
    assert report["wx_mmap_errno"] == 1
    assert report["plan_ok"] is True and report["compiled_steps"] == 3 and report["compiled_unavailable"] is None


def _syscall_groups() -> dict[str, set[str]]:
    assert ANALYZE is not None
    out = subprocess.run(
        [ANALYZE, "syscall-filter", "--no-pager"], capture_output=True, text=True, timeout=60
    ).stdout
    groups: dict[str, set[str]] = {}
    current: set[str] | None = None
    for line in out.splitlines():
        if line.startswith("@"):
            current = groups.setdefault(line.strip(), set())
        elif not line.startswith((" ", "\t")):
            current = None
        elif current is not None and line.strip() and not line.strip().startswith("#"):
            current.add(line.strip())
    return groups


def _expand(names: list[str], groups: dict[str, set[str]]) -> set[str]:
    out: set[str] = set()
    for name in names:
        out |= _expand(sorted(groups[name]), groups) if name.startswith("@") else {name}
    return out


def _unit_syscall_allowlist() -> set[str]:
    groups = _syscall_groups()
    allowed: set[str] = set()
    for value in _directives(UNIT.read_text())["SystemCallFilter"]:
        deny = value.startswith("~")
        names = _expand(value.lstrip("~").split(), groups)
        allowed = allowed - names if deny else allowed | names
    return allowed


def _traced_syscalls(summary: str) -> set[str]:
    names: set[str] = set()
    in_table = False
    for line in summary.splitlines():
        if line.startswith("------"):
            in_table = not in_table
            continue
        if in_table and line.strip():
            names.add(line.split()[-1])
    return names


@needs_analyze
@pytest.mark.skipif(STRACE is None, reason="strace not installed (apt-get install strace)")
def test_service_stack_syscalls_are_inside_the_unit_filter(tmp_path: Path) -> None:
    allowed = _unit_syscall_allowlist()
    assert {"read", "sendto", "epoll_wait"} <= allowed and "reboot" not in allowed
    summary = tmp_path / "strace.txt"
    assert STRACE is not None
    _run_sandboxed(tmp_path, [STRACE, "-f", "-c", "-o", str(summary)])
    used = _traced_syscalls(summary.read_text())
    assert len(used) > 20, summary.read_text()
    # prctl/seccomp come from the emulation harness itself, not from the service.
    assert used - allowed - {"seccomp"} == set()


# --- sd_notify ---------------------------------------------------------------------------------


def _receiver(tmp_path: Path, abstract: bool) -> tuple[socket.socket, str]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    if abstract:
        name = f"bezier-test-{os.getpid()}-{tmp_path.name}"
        sock.bind("\0" + name)
        env_value = "@" + name
    else:
        env_value = str(tmp_path / "notify.sock")
        sock.bind(env_value)
    sock.settimeout(2)
    return sock, env_value


def _fields(sock: socket.socket) -> dict[str, str]:
    data = sock.recv(4096).decode()
    return dict(line.split("=", 1) for line in data.splitlines())


@pytest.mark.parametrize("abstract", [False, True])
def test_notifier_sends_ready_status_watchdog_stopping(tmp_path: Path, abstract: bool) -> None:
    sock, address = _receiver(tmp_path, abstract)
    env = {"NOTIFY_SOCKET": address, "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid())}
    with sock, Notifier(env) as notifier:
        assert notifier.ready("planning\nready") is True
        ready = _fields(sock)
        assert ready["READY"] == "1" and ready["MAINPID"] == str(os.getpid())
        assert ready["STATUS"] == "planning ready"  # a newline would have forged a field
        assert notifier.watchdog() is True
        assert _fields(sock) == {"WATCHDOG": "1"}
        assert notifier.status("streaming 50 Hz") is True
        assert _fields(sock) == {"STATUS": "streaming 50 Hz"}
        assert notifier.stopping() is True
        assert _fields(sock) == {"STOPPING": "1"}


def test_watchdog_is_rate_limited_to_a_quarter_interval(tmp_path: Path) -> None:
    sock, address = _receiver(tmp_path, False)
    now = [100.0]
    env = {"NOTIFY_SOCKET": address, "WATCHDOG_USEC": "2000000"}
    with sock, Notifier(env, clock=lambda: now[0]) as notifier:
        sent = []
        for _ in range(200):  # 4 s of 50 Hz setpoint ticks
            sent.append(notifier.watchdog())
            now[0] += 0.02
        sock.setblocking(False)
        received = 0
        while True:
            try:
                assert sock.recv(64) == b"WATCHDOG=1"
            except BlockingIOError:
                break
            received += 1
    assert received == sum(sent)
    # every 0.5 s over 4 s: 8 pings, never two closer than interval/4
    assert 7 <= received <= 9
    gaps = [i for i, s in enumerate(sent) if s]
    assert min(b - a for a, b in itertools.pairwise(gaps)) * 0.02 >= 0.5 - 1e-9


def test_notifier_is_a_no_op_outside_systemd() -> None:
    notifier = Notifier({})
    assert not notifier.enabled and not notifier.watchdog_enabled
    assert notifier.ready() is False and notifier.watchdog() is False
    assert notifier.stopping() is False


def test_notifier_survives_a_vanished_socket(tmp_path: Path) -> None:
    with Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone.sock")}) as notifier:
        assert notifier.enabled
        assert notifier.ready() is False


@pytest.mark.parametrize(
    ("env", "expected"),
    [
        ({}, None),
        ({"WATCHDOG_USEC": "2000000"}, 2.0),
        ({"WATCHDOG_USEC": "500000", "WATCHDOG_PID": str(os.getpid())}, 0.5),
        ({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"}, None),
        ({"WATCHDOG_USEC": "0"}, None),
        ({"WATCHDOG_USEC": "soon"}, None),
    ],
)
def test_watchdog_interval(env: dict[str, str], expected: float | None) -> None:
    assert watchdog_interval(env) == expected


# --- the real service under the emulated sandbox -----------------------------------------------


def _free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _fifo_permitted() -> bool:
    chrt = shutil.which("chrt")
    return chrt is not None and subprocess.run([chrt, "-f", "1", "true"], capture_output=True).returncode == 0


def _thread_policies(pid: int) -> dict[int, tuple[str, str]]:
    """tid -> (thread name, scheduling policy) for a process and all its descendants."""
    out: dict[int, tuple[str, str]] = {}
    todo = [pid]
    while todo:
        p = todo.pop()
        with contextlib.suppress(OSError):
            for task in Path(f"/proc/{p}/task").iterdir():
                tid = int(task.name)
                with contextlib.suppress(OSError):
                    name = (task / "comm").read_text().strip()
                    policy = os.sched_getscheduler(tid)
                    todo += [int(c) for c in (task / "children").read_text().split()]
                    out[tid] = (name, {os.SCHED_FIFO: "fifo", os.SCHED_RR: "rr"}.get(policy, "normal"))
    return out


def test_unit_grants_fifo_that_the_service_keeps_for_its_setpoint_thread() -> None:
    """CPUSchedulingPolicy= is set by systemd before the sandbox: the service gets SCHED_FIFO
    without a capability and cannot acquire it again (RestrictRealtime=yes); it must be able
    to leave it (sched_setscheduler allowed), and its setpoint thread must inherit it (so no
    CPUSchedulingResetOnFork=yes)."""
    d = _directives(UNIT.read_text())
    assert d["CPUSchedulingPolicy"] == ["fifo"]
    priority = int(d["CPUSchedulingPriority"][-1])
    assert 1 <= priority < 50  # below the kernel's interrupt threads
    assert d.get("CPUSchedulingResetOnFork", ["no"])[-1] in ("no", "false", "0")
    assert d["RestrictRealtime"] == ["yes"] and d["CapabilityBoundingSet"] == [""]
    assert d["AmbientCapabilities"] == [""] and "LimitRTPRIO" not in d
    assert any("sched_setscheduler" in v.split() for v in d["SystemCallFilter"] if not v.startswith("~"))


@pytest.mark.skipif(sys.platform != "linux" or not _fifo_permitted(), reason="needs Linux and SCHED_FIFO")
def test_restrict_realtime_emulation_lets_a_policy_be_left_never_acquired(tmp_path: Path) -> None:
    sandbox = tmp_path / "sandbox.py"
    sandbox.write_text(SANDBOX)
    probe = tmp_path / "probe.py"
    probe.write_text(textwrap.dedent("""
        import json, os
        out = {"start": os.sched_getscheduler(0)}
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        out["left"] = os.sched_getscheduler(0)
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            out["acquire"] = "allowed"
        except PermissionError:
            out["acquire"] = "EPERM"
        print("REPORT " + json.dumps(out))
    """))
    env = dict(os.environ, EMULATE_MDWE="0", EMULATE_RESTRICT_REALTIME="1")
    proc = subprocess.run(["chrt", "-f", "3", sys.executable, str(sandbox), str(probe)], env=env,
                          capture_output=True, text=True, timeout=60)
    line = next(x for x in proc.stdout.splitlines() if x.startswith("REPORT "))
    out = json.loads(line[len("REPORT "):])
    # as root (CAP_SYS_NICE) the last call would succeed without the rule: the rule refused it
    assert out == {"start": os.SCHED_FIFO, "left": os.SCHED_OTHER, "acquire": "EPERM"}, proc.stderr


@pytest.mark.skipif(sys.platform != "linux", reason="seccomp is Linux-only")
def test_companion_runs_sandboxed_and_speaks_sd_notify(tmp_path: Path) -> None:
    """The service as systemd would run it: sandbox rules, NOTIFY_SOCKET and WATCHDOG_USEC set,
    and (where this machine permits it) started under the unit's SCHED_FIFO with
    RestrictRealtime= in force.

    It must come up (READY=1), keep pinging the watchdog as its setpoints go out, plan a mission
    sent over Zenoh, run no thread but its setpoint thread realtime (planner processes
    included), stay inside the unit's syscall filter (when strace is there to tell), and stop
    cleanly on SIGTERM (STOPPING=1, exit 0).
    """
    from companion.config import config_to_toml
    from demo.rig import Child, Peer, demo_config

    mav_port, zenoh_port = _free_port(socket.SOCK_DGRAM), _free_port(socket.SOCK_STREAM)
    cfg = demo_config(zenoh_port, mav_port)
    cfg_path = tmp_path / "uav.toml"
    cfg_path.write_text(config_to_toml(cfg))
    sandbox = tmp_path / "sandbox.py"
    sandbox.write_text(SANDBOX)
    notify, address = _receiver(tmp_path, abstract=True)
    env = dict(os.environ, NOTIFY_SOCKET=address, WATCHDOG_USEC="2000000", EMULATE_RESTRICT_REALTIME="1",
               **_unit_environment())
    summary = tmp_path / "strace.txt"
    tracer = [STRACE, "-f", "-c", "-o", str(summary)] if STRACE and ANALYZE else []
    fifo = _fifo_permitted()
    priority = _directives(UNIT.read_text())["CPUSchedulingPriority"][-1]
    scheduler = ["chrt", "-f", priority] if fifo else []  # what CPUSchedulingPolicy=fifo does
    mock = Child("mock", [sys.executable, "-m", "sitl_mock", "--endpoint", f"udpin:127.0.0.1:{mav_port}",
                          "--px4-ready-after", "0"],  # PX4's estimator settling is not this test's subject
                 tmp_path / "mock.log")
    proc = subprocess.Popen(
        [*scheduler, *tracer, sys.executable, str(sandbox), "-m", "companion", "run", "--config", str(cfg_path)],
        env=env, cwd=ROOT, stdout=(tmp_path / "companion.log").open("wb"), stderr=subprocess.STDOUT,
    )
    received: list[dict[str, str]] = []
    policies: dict[int, tuple[str, str]] = {}
    peer: Peer | None = None
    try:
        notify.settimeout(60)
        received.append(_fields(notify))
        assert received[0].get("READY") == "1", received
        peer = Peer(f"tcp/127.0.0.1:{zenoh_port}", cfg.vehicle.id)
        deadline = time.monotonic() + 30
        while not (peer.query("status", 1.0) or {}).get("link") and time.monotonic() < deadline:
            time.sleep(0.2)
        t_put = peer.put("mission", {"id": "sandboxed", "frame": "enu", "waypoints": [[2, 1, 3], [4, 0, 3]]})
        accepted = None
        while accepted is None and time.monotonic() < t_put + 30:
            sample = peer.samples.get(timeout=30)
            if sample.topic == "events" and sample.data.get("key") == "mission":
                accepted = sample.data
        notify.settimeout(5)
        pings = 0
        while pings < 2:
            fields = _fields(notify)
            received.append(fields)
            pings += fields.get("WATCHDOG") == "1"
        policies = _thread_policies(proc.pid)
    finally:
        if peer is not None:
            peer.close()
        # as systemd would: SIGTERM to the main process (under strace, strace's child)
        main_pid = proc.pid
        if tracer:
            with contextlib.suppress(OSError):
                children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
                main_pid = int(children[0]) if children else proc.pid
        with contextlib.suppress(ProcessLookupError):
            os.kill(main_pid, signal.SIGTERM)
        code: int | None = None
        try:
            code = proc.wait(30)
        except subprocess.TimeoutExpired:
            for pid in {main_pid, proc.pid}:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            proc.wait(10)
        finally:
            mock.stop()
        notify.setblocking(False)
        with contextlib.suppress(BlockingIOError):
            while True:
                received.append(dict(line.split("=", 1) for line in notify.recv(4096).decode().splitlines()))
        notify.close()
    log = (tmp_path / "companion.log").read_text(errors="replace")
    assert accepted is not None and accepted["type"] == "accepted", log[-3000:]
    assert code == 0, log[-3000:]
    assert any(f.get("STOPPING") == "1" for f in received), received
    if fifo:
        # the tracer (when there) keeps the policy it was started with; the service's own tree
        # has exactly one realtime thread, the setpoint thread; the planner processes exist
        service = {tid: v for tid, v in policies.items() if v[0] != "strace"}
        assert [v for v in service.values() if v[1] != "normal"] == [("setpoints", "fifo")], policies
        # the setpoint stream runs in a thread of the service or a process of its own ([setpoints] process)
        assert re.search(rf"setpoint (thread|process): 50 Hz, fifo {priority} scheduling", log), log[-3000:]
        assert len(service) > 10, policies
    if tracer:
        used = _traced_syscalls(summary.read_text())
        assert used - _unit_syscall_allowlist() - {"seccomp"} == set()
