"""The setpoint stream from a process of its own (`[setpoints] process = true`, the default).

A thread of the service's own process needs the GIL for every tick, and on a loaded computer
under normal scheduling the GIL is not there when it is needed: a long C call in another thread
(unpickling a plan, a big JSON decode, numpy work) or a garbage collection of the service's
heap keeps it for hundreds of milliseconds (issue 21: 756 ms measured, the flight ended in
FAILSAFE). A process of its own has a GIL and a heap of its own, both nearly empty: it samples
the current verified trajectory and writes each setpoint to the autopilot's socket itself.

What crosses between the processes:
- parent -> child, one pipe (`multiprocessing.Connection`), read by the child between ticks:
  the feed (trajectory, time base, yaw) as a whole, the lead, where the autopilot is (the
  route), every other MAVLink message the service sends (so one writer owns the link's packet
  sequence and signing timestamps; see `MavlinkLink.use_writer`), the descriptor to write to
  when a TCP link is connected again (or none while it is down), stop;
- child -> parent, a non-blocking pipe of fixed-size records, one per tick: the child never
  waits for the parent (a full pipe drops records, counted), the parent turns them back into
  `Tick`s for the loop exactly as the thread did;
- `setpoints.Liveness` lives in shared memory, so the loop's pulse and the stall latch work
  across the two processes as they did across the two threads.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import multiprocessing
import multiprocessing.connection
import os
import signal
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing import reduction, resource_tracker, shared_memory
from typing import Any, cast

import numpy as np

from companion.setpoints import (
    THREAD_STALL,
    AimTerms,
    DeadlineScheduler,
    Feed,
    Liveness,
    Setpoint,
    Tick,
    YawPolicy,
    name_thread,
    realtime_here,
    sample,
)
from planner_core import Trajectory

log = logging.getLogger("companion")

# One tick record: kind, now, deadline, next_deadline, feed id, gap, errno, records dropped so
# far, p(3), v(3), a(3), yaw. 18 doubles = 144 bytes, well under PIPE_BUF: a write to the pipe is
# whole or refused, never torn.
_RECORD = struct.Struct("<18d")
_TICK, _HELLO = 0.0, 1.0
_SCHEDULING = {0: "normal"}  # hello's code -> text; other codes: "fifo N" (N = code) or "rr N" (-N)
_FEEDS_KEPT = 8  # feeds remembered by id: the active one and the few being swapped in


class _Fd:
    """A file descriptor handed to the spawned child (multiprocessing duplicates it, as it
    does for sockets), for the link's socket or serial device, whatever its kind."""

    def __init__(self, fd: int) -> None:
        self.fd = fd

    def __reduce__(self) -> tuple[Any, ...]:
        return (_rebuild_fd, (reduction.DupFd(self.fd),))


def _rebuild_fd(dup: Any) -> int:
    return int(dup.detach())


@dataclass(frozen=True)
class Encoding:
    """How the child packs setpoints: who we are, who the autopilot is, and the signing key."""

    sysid: int
    component: int
    target_system: int
    target_component: int
    signing_key: bytes | None
    boot: float  # monotonic instant of time_boot_ms 0


@dataclass(frozen=True)
class _Start:
    rate: float
    fd: _Fd | None  # an int in the child; None: a TCP link not connected yet
    datagram: bool  # a UDP socket: sendto the route; else write to the stream/device
    encoding: Encoding
    yaw: tuple[str, float, float]  # YawPolicy(mode, fixed, min_speed)
    priority: int
    liveness: Any  # setpoints.Liveness (shared memory)
    sent: Any  # a shared counter of the setpoints the child wrote


class SetpointProcess:
    """`SetpointSender`'s surface (feed, lead, liveness, start, stop, withheld, native_id,
    scheduling) with the stream in a child process."""

    def __init__(self, rate: float, transport: Callable[[], tuple[int | None, bool, Encoding]], yaw: YawPolicy,
                 on_tick: Callable[[Tick], None], on_failure: Callable[[BaseException], None],
                 priority: int = 0) -> None:
        self.rate = rate
        self.yaw = yaw
        self.on_tick = on_tick
        self.on_failure = on_failure
        self.priority = priority
        self.liveness: Liveness | None = None
        self.scheduling = "normal"
        self.native_id: int | None = None
        self.dropped_records = 0  # tick records the child could not hand over (the parent was slow)
        # written by the child alone, read by the loop's watchdog: counts the setpoints that left
        # even while the loop is too busy to take the tick records
        self._sent: Any = multiprocessing.get_context("spawn").RawValue("Q", 0)
        self._transport = transport  # (descriptor, is a datagram socket, encoding), once the link is open
        self._feed: Feed | None = None
        self._lead = 0.0
        self._accel_lead = 0.0  # s²: setpoints.sample
        self._accel_lead_tc = 0.0  # s
        self._aim_horizontal: AimTerms = ()
        self._feeds: dict[int, Feed] = {}
        self._segments: list[str] = []  # shared memory handed to the child, newest last
        self._next_id = 0
        self._route: tuple[Any, ...] = ()
        self._lock = threading.Lock()  # one writer of the command pipe at a time
        self._proc: Any = None
        self._to_child: multiprocessing.connection.Connection | None = None
        self._records = -1
        self._reader: threading.Thread | None = None
        self._stopping = False
        self._gone = False  # the child's records ended: it is dead, whatever is_alive says yet
        self._hello = threading.Event()

    # -- what the loop sets ----------------------------------------------------------------------

    @property
    def feed(self) -> Feed | None:
        return self._feed

    @feed.setter
    def feed(self, feed: Feed | None) -> None:
        self._feed = feed
        if feed is None:
            self._post(("feed", None))
            return
        self._next_id += 1
        self._feeds[self._next_id] = feed
        if len(self._feeds) > _FEEDS_KEPT:
            del self._feeds[min(self._feeds)]
        # The curve's numbers go through shared memory and the pipe carries only its name: a
        # plan of 1000 segments pickled with its corridors is ~1 MB, which the child would read
        # from the 64 kB pipe in pieces, waiting on a busy parent for each (missed ticks).
        traj = feed.trajectory
        times = np.ascontiguousarray(traj.times, dtype=float)
        points = np.ascontiguousarray(traj.control_points, dtype=float)
        shm = shared_memory.SharedMemory(create=True, size=times.nbytes + points.nbytes)
        # the child unlinks it once read; not the resource tracker's to clean up at our exit
        resource_tracker.unregister(shm._name, "shared_memory")  # type: ignore[attr-defined]
        buf = shm.buf
        assert buf is not None
        buf[: times.nbytes] = times.tobytes()
        buf[times.nbytes:] = points.tobytes()
        del buf
        self._segments.append(shm.name)
        del self._segments[:-_FEEDS_KEPT]
        shm.close()
        self._post(("feed", (self._next_id, shm.name, times.shape, points.shape, feed.t_base, self.yaw.last)))

    @property
    def lead(self) -> float:
        return self._lead

    @lead.setter
    def lead(self, lead: float) -> None:
        if lead != self._lead:
            self._lead = lead
            self._post(("lead", float(lead)))

    @property
    def accel_lead(self) -> float:
        return self._accel_lead

    @accel_lead.setter
    def accel_lead(self, k: float) -> None:
        if k != self._accel_lead:
            self._accel_lead = k
            self._post(("accel_lead", float(k)))

    @property
    def accel_lead_tc(self) -> float:
        return self._accel_lead_tc

    @accel_lead_tc.setter
    def accel_lead_tc(self, tc: float) -> None:
        if tc != self._accel_lead_tc:
            self._accel_lead_tc = tc
            self._post(("accel_lead_tc", float(tc)))

    @property
    def aim_horizontal(self) -> AimTerms:
        return self._aim_horizontal

    @aim_horizontal.setter
    def aim_horizontal(self, terms: AimTerms) -> None:
        if terms != self._aim_horizontal:
            self._aim_horizontal = terms
            self._post(("aim_horizontal", terms))

    def route(self, addresses: tuple[Any, ...]) -> None:
        """Where datagrams go (the autopilot's address), whenever the link learns or changes it."""
        if addresses != self._route:
            self._route = addresses
            self._post(("route", addresses))

    def use_fd(self, fd: int | None) -> None:
        """Write to `fd` from now on (a TCP link connected again), or to nothing (None: lost).
        The child gets its own copy of `fd` (multiprocessing's resource sharer passes it), and
        closes the copy it had: the old connection is not kept half-open by the child."""
        self._post(("fd", None if fd is None else _Fd(fd)))

    def post_message(self, msg: Any) -> bool:
        """Have the child pack (its sequence numbers and signature) and write `msg`."""
        return self._post(("message", msg))

    @property
    def sent(self) -> int:
        """Setpoints the child has written so far."""
        return int(self._sent.value)

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.is_alive() and not self._stopping

    @property
    def withheld(self) -> bool:
        return self.liveness is not None and self.liveness.withheld is not None

    def _post(self, item: tuple[str, Any]) -> bool:
        conn = self._to_child
        # a dead child's pipe may still take bytes into its buffer: those would never be written,
        # and a hand-over sent that way is lost (the caller writes itself when this says False)
        if conn is None or self._stopping or self._gone or not (self._proc is not None and self._proc.is_alive()):
            return False
        try:
            with self._lock:
                conn.send(item)
        except (OSError, ValueError):  # the child is gone: the reader reports it
            return False
        return True

    # -- life ------------------------------------------------------------------------------------

    def start(self, starter: Callable[[Callable[[], None]], threading.Thread] | None = None) -> None:
        """Spawn the child (from `starter`'s thread when given, e.g. companion.rtsched's reserved
        realtime thread, so that the child inherits its policy); returns once it runs."""
        ctx = multiprocessing.get_context("spawn")
        child_end, self._to_child = ctx.Pipe(duplex=False)
        rd, wr = os.pipe()
        os.set_blocking(wr, False)
        self._records = rd
        fd, datagram, encoding = self._transport()
        start = _Start(self.rate, None if fd is None else _Fd(fd), datagram, encoding,
                       (self.yaw.mode, self.yaw.last, self.yaw.min_speed), self.priority, self.liveness, self._sent)
        self._proc = ctx.Process(target=_child_main, args=(start, child_end, _Fd(wr)),
                                 name="companion-setpoints", daemon=True)
        spawned = threading.Event()
        failed: list[BaseException] = []

        def spawn() -> None:
            try:
                self._proc.start()
            except BaseException as exc:
                failed.append(exc)
            spawned.set()

        if starter is not None:
            starter(spawn)
        else:
            spawn()
        spawned.wait(30.0)
        os.close(wr)
        child_end.close()  # the child's copy only: a dead child's pipe then refuses our writes
        if failed:
            raise failed[0]
        self._reader = threading.Thread(target=self._read_records, name="setpoint-ticks", daemon=True)
        self._reader.start()
        self._hello.wait(30.0)
        if self._route:
            self._post(("route", self._route))
        # the lead set before the child ran (the service sets the initial one at construction,
        # the autopilot's at link-up) was not posted: without it the child samples at lead 0
        # while the parent believes otherwise, and the first change of the lead makes the
        # stream jump along the plan by the whole lead
        self._post(("lead", self._lead))
        self._post(("accel_lead", self._accel_lead))
        self._post(("accel_lead_tc", self._accel_lead_tc))
        self._post(("aim_horizontal", self._aim_horizontal))

    def stop(self, timeout: float = 2.0) -> None:
        if self._proc is None:
            return
        self._post(("stop", None))
        self._stopping = True
        self._proc.join(timeout)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(1.0)
        if self._to_child is not None:
            self._to_child.close()
            self._to_child = None
        for name in self._segments:  # the child unlinks what it read; what it never read is ours
            with contextlib.suppress(FileNotFoundError):
                seg = shared_memory.SharedMemory(name=name)
                seg.close()
                seg.unlink()
        self._segments.clear()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(timeout)

    # -- ticks back from the child -------------------------------------------------------------

    def _read_records(self) -> None:
        name_thread("setpoint-ticks")
        buf = b""
        with open(self._records, "rb", buffering=0) as pipe:
            while True:
                try:
                    chunk = pipe.read(_RECORD.size * 64)
                except OSError:
                    chunk = b""
                if not chunk:
                    break
                buf += chunk
                whole = len(buf) - len(buf) % _RECORD.size
                for off in range(0, whole, _RECORD.size):
                    self._record(_RECORD.unpack_from(buf, off))
                buf = buf[whole:]
        self._gone = True
        if not self._stopping:
            code = self._proc.exitcode if self._proc is not None else None
            self.on_failure(RuntimeError(f"the setpoint process exited (code {code})"))

    def _record(self, r: tuple[float, ...]) -> None:
        if r[0] == _HELLO:
            self.native_id = int(r[1])
            code = int(r[2])
            self.scheduling = _SCHEDULING.get(code, f"fifo {code}" if code > 0 else f"rr {-code}")
            self._hello.set()
            return
        now, deadline, next_deadline, feed_id, gap, err, dropped = r[1:8]
        self.dropped_records = int(dropped)
        feed = self._feeds.get(int(feed_id)) if feed_id > 0 else None
        sp = None
        if feed is not None:
            sp = Setpoint(np.array(r[8:11]), np.array(r[11:14]), np.array(r[14:17]), float(r[17]))
            self.yaw.last = float(r[17])  # immediate sends from the loop continue from here
        error = OSError(int(err), os.strerror(int(err))) if err > 0 else None
        self.on_tick(Tick(now, deadline, next_deadline, feed, sp, None if math.isnan(gap) else gap, error))


# -- the child ----------------------------------------------------------------------------------


def _scheduling_code(text: str) -> int:
    kind, _, prio = text.partition(" ")
    if kind == "fifo":
        return int(prio)
    if kind == "rr":
        return -int(prio)
    return 0


class _Writer:
    """The child's side of the link: packs with its own sequence and signing state, writes."""

    def __init__(self, start: _Start, fd: int | None) -> None:
        os.environ.setdefault("MAVLINK20", "1")
        from pymavlink import mavutil

        e = start.encoding
        self.enc = e
        self.mav = mavutil.mavlink.MAVLink(None, srcSystem=e.sysid, srcComponent=e.component)
        if e.signing_key is not None:
            s = self.mav.signing
            s.secret_key = e.signing_key
            s.sign_outgoing = True
            s.link_id = 0
            # 10 us units since 2015-01-01 (the spec's epoch), as pymavlink's setup_signing
            s.timestamp = int((time.time() - 1420070400) * 100000)
        self.fd = fd
        self.datagram = start.datagram
        self.sock: Any = None
        if self.datagram:
            import socket

            self.sock = socket.socket(fileno=fd)
        self.route: tuple[Any, ...] = ()  # the autopilot's address(es), from the parent

    def use_fd(self, fd: int | None) -> None:
        """A stream link's new descriptor (a TCP link connected again), or None while it is down."""
        if self.fd is not None and self.fd != fd:
            with contextlib.suppress(OSError):
                os.close(self.fd)
        self.fd = fd

    def write(self, packet: bytes) -> None:
        if self.datagram:
            for address in self.route:
                self.sock.sendto(packet, address)
        elif self.fd is None:
            # a setpoint that did not leave is not counted as sent, and its tick says why
            raise OSError(errno.ENOTCONN, "no connection to the autopilot (reconnecting)")
        else:
            os.write(self.fd, packet)

    def pack(self, msg: Any) -> bytes:
        packet = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return packet

    def setpoint(self, sp: Setpoint) -> bytes:
        p, v, a = sp.position, sp.velocity, sp.acceleration
        e = self.enc
        msg = self.mav.set_position_target_local_ned_encode(
            int((time.monotonic() - e.boot) * 1000) & 0xFFFFFFFF, e.target_system, e.target_component,
            1, 2048,  # MAV_FRAME_LOCAL_NED; position + velocity + acceleration + yaw
            float(p[0]), float(p[1]), float(p[2]), float(v[0]), float(v[1]), float(v[2]),
            float(a[0]), float(a[1]), float(a[2]), float(sp.yaw), 0.0)
        return self.pack(msg)


def _read_curve(name: str, t_shape: tuple[int, ...], p_shape: tuple[int, ...]) -> Trajectory:
    """The curve the parent put in shared memory `name` (times, control points), copied out; the
    segment is unlinked (its one reader is done with it)."""
    seg = shared_memory.SharedMemory(name=name)  # (3.11 registers it with the tracker; unlink unregisters)
    try:
        buf = seg.buf
        assert buf is not None
        n_t = int(np.prod(t_shape)) * 8
        times = np.frombuffer(buf[:n_t], dtype=float).reshape(t_shape).copy()
        points = np.frombuffer(buf[n_t:n_t + int(np.prod(p_shape)) * 8], dtype=float).reshape(p_shape).copy()
        del buf
    finally:
        seg.close()
        with contextlib.suppress(FileNotFoundError):
            seg.unlink()
    return Trajectory(times, points)


def _child_main(start: _Start, inbox: multiprocessing.connection.Connection, records_fd: Any) -> None:
    # `start.fd` and `records_fd` arrive here as plain descriptors (_Fd's reduction), or None.
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the service stops us (first signal: hand-over)
    name_thread("setpoints")
    parent = os.getppid()
    out = int(records_fd)
    writer = _Writer(start, cast("int | None", start.fd))
    scheduling = realtime_here(start.priority)
    dropped = 0
    mode, fixed, min_speed = start.yaw
    yaw = YawPolicy(mode, fixed, min_speed)

    def record(values: tuple[float, ...]) -> None:
        nonlocal dropped
        try:
            os.write(out, _RECORD.pack(*values))
        except BlockingIOError:
            dropped += 1  # the parent is behind: the stream goes on, its bookkeeping waits
        except BrokenPipeError:
            raise SystemExit(0) from None

    live: Liveness | None = start.liveness
    feed: tuple[int, Feed] | None = None
    lead = 0.0
    accel_lead = 0.0
    accel_lead_tc = 0.0
    aim_horizontal: AimTerms = ()

    def handle(kind: str, body: Any) -> bool:
        """One item from the parent; False: stop."""
        nonlocal feed, lead, accel_lead, accel_lead_tc, aim_horizontal
        if kind == "feed":
            if body is None:
                feed = None
            else:
                fid, name, t_shape, p_shape, t_base, yaw_last = body
                feed = (fid, Feed(_read_curve(name, t_shape, p_shape), t_base))
                yaw.last = yaw_last
        elif kind == "lead":
            lead = body
        elif kind == "accel_lead":
            accel_lead = body
        elif kind == "accel_lead_tc":
            accel_lead_tc = body
        elif kind == "aim_horizontal":
            aim_horizontal = body
        elif kind == "route":
            writer.route = body
        elif kind == "fd":
            writer.use_fd(None if body is None else int(body))
        elif kind == "message":
            with contextlib.suppress(OSError):
                writer.write(writer.pack(body))
        elif kind == "stop":
            return False
        return True

    def drain(timeout: float) -> bool:
        """Handle what the parent sent, waiting at most `timeout` for the first item."""
        while inbox.poll(timeout):
            try:
                kind, body = inbox.recv()
            except (EOFError, OSError):
                return False  # the service is gone
            if not handle(kind, body):
                return False
            timeout = 0.0
        return os.getppid() == parent

    # Pay for the imports and first calls of sampling and packing now: the first feed arrives when
    # the companion takes control, and must fly from its first tick (PX4 counts the warm-up).
    from planner_core import hold

    warm = hold(np.zeros(3), 0.0)
    writer.setpoint(sample(warm, 0.0, yaw))
    writer.mav.seq = 0
    record((_HELLO, float(os.getpid()), float(_scheduling_code(scheduling)), *([0.0] * 15)))
    sched = DeadlineScheduler(time.monotonic(), start.rate)
    last: float | None = None
    woke = time.monotonic()
    deadline = sched.next_deadline(woke)
    while True:
        # Until the deadline, whatever the parent sends is handled at once (a swap's immediate
        # setpoint, a command); at the deadline, what arrived meanwhile, then the tick.
        while (delay := deadline - time.monotonic()) > 0:
            if not drain(delay):
                return
        if not drain(0.0):
            return
        now = time.monotonic()
        thread_gap, woke = now - woke, now
        current = feed
        # a stall after a setpoint left is latched even when the stream was released meanwhile
        # (as in setpoints.SetpointSender._run: the stall is still the cause, and is said)
        if live is not None and (current is not None or (last is not None and thread_gap > THREAD_STALL)) \
                and not live.check(now, thread_gap):
            current = None
        following = sched.deadline(sched.k + 1)
        if current is not None:
            fid, f = current
            sp = sample(f.trajectory, now - f.t_base + lead, yaw, accel_lead, accel_lead_tc, aim_horizontal)
            err = 0
            try:
                writer.write(writer.setpoint(sp))
                start.sent.value += 1
            except OSError as exc:
                err = exc.errno or errno.EIO
            gap = math.nan if last is None else now - last
            last = now
            record((_TICK, now, deadline, following, float(fid), gap, float(err), float(dropped),
                    *sp.position, *sp.velocity, *sp.acceleration, sp.yaw))
        else:
            last = None
            record((_TICK, now, deadline, following, -1.0, math.nan, 0.0, float(dropped), *([0.0] * 10)))
        deadline = sched.next_deadline(time.monotonic())
