"""What the autopilot reports, and how the vehicle's situation follows it.

Heartbeats (armed first, then mode), the landed state, EVENT/STATUSTEXT and link loss are
submitted to the supervisor as events; it decides (companion/supervisor.py): a mode we did not
ask for is a pilot takeover and a disarm we did not ask for a failsafe: control is released at
once and never retaken without a new `start`. While the companion itself is stalled (or just
woke from a stall), what the autopilot did meanwhile is put down to that stall, not to a pilot
or to the link.

Which event each message makes is decided by a pure function, companion.autopilot_rules.watch_step
(`now` an input, the watch's memory a frozen `WatchState`); this class reads the link into its
typed readings, shows every call to an observer (the flight recorder: /autopilot/step, replayed by
`python -m companion replay`) and carries out what the rules return. The telemetry requests and
the advice about what does not arrive (timers, tasks, the link's answers) stay here, unreplayed.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import math
import re
import time
from collections.abc import Callable
from typing import Any

from companion.autopilot_rules import (
    AIR_HEIGHT,
    GROUND_FOR,
    GROUND_HEIGHT,
    GROUND_SPEED,
    LANDED_STATE_STALE,
    WATCH_EVENTS,
    HeartbeatSeen,
    LandedStateSeen,
    LinkCheck,
    LinkFound,
    LinkRestored,
    NoteSeen,
    Output,
    PositionSeen,
    Reading,
    WatchRules,
    WatchState,
    watch_step,
)
from companion.config import Config
from companion.flight import FlightState
from companion.report import Reporter
from companion.supervisor import HeightReport, Supervisor
from companion.wire.mavlink import MavlinkLink
from companion.wire.vehicle import WANTED, CommandFailed, Note

log = logging.getLogger("companion")
# What an autopilot says while it has no position estimate (ArduPilot PreArm texts, PX4 events).
ESTIMATE_WORDS = re.compile(r"EKF|GPS|origin|position estimate|attitude estimate|local_pos|estimator|"
                            r"check_modes_attitude|check_estimator", re.IGNORECASE)
# What PX4 sends only once its estimator is ready, whatever the interval requests say.
PX4_ESTIMATED = ("ATTITUDE", "LOCAL_POSITION_NED")
EVENTS_KEPT = 128  # PX4 EVENTs kept: a whole arming-check report (~10) with room to spare
TELEMETRY_CHECK = 3.0  # s after the requests: what has not arrived by then is reported
WAITING_EVERY = 5.0  # s between "waiting for autopilot heartbeat" lines
# the height rule's thresholds live with the rules (companion.autopilot_rules); named here too
__all__ = ["AIR_HEIGHT", "GROUND_FOR", "GROUND_HEIGHT", "GROUND_SPEED", "LANDED_STATE_STALE", "AutopilotWatch",
           "StepObserver", "waiting_hint"]
# what an observer of the rules is shown, once per call: the watch's state before, the flight
# state the rules read, the reading, the time, the watch's state after and the outputs
StepObserver = Callable[[WatchState, FlightState, Reading, float, WatchState, tuple[Output, ...]], None]


def _unobserved(*_call: Any) -> None:
    pass


def waiting_hint(url: str) -> str:
    """What a companion waiting for a first heartbeat listens on, and the usual causes."""
    kind, _, rest = url.partition(":")
    if kind == "udpin":
        where = (f"listening on UDP {rest}: the autopilot (or mavlink-router) must send to this port; usual "
                 "causes: it sends to another port or host (PX4 SITL sends from 14580 to 14540), the port here "
                 "is wrong, or the mock was started with other ports (python -m sitl_mock sends to "
                 "127.0.0.1:14540 from 14580 by default; with --endpoint udpin:HOST:PORT it listens instead, and "
                 "the companion must use udpout:HOST:PORT)")
    elif kind in ("udpout", "udp"):
        where = (f"sending heartbeats to UDP {rest} and listening for the answer: usual causes: nothing listens "
                 "there (a mock or autopilot that sends rather than listens needs udpin: here), or a firewall")
    elif kind == "tcpin":
        where = (f"listening on TCP {rest}: the autopilot (or mavlink-router) must connect here; usual causes: "
                 "it dials another port or host, it has not started yet, or it listens too (ArduPilot SITL "
                 "serves tcp:127.0.0.1:5760 unless told --serial0 tcpclient:HOST:PORT: use tcp: here then)")
    elif kind == "tcp":
        where = (f"connecting to TCP {rest}: usual causes: nothing listens there (ArduPilot SITL serves "
                 "tcp:127.0.0.1:5760) or it has not started yet")
    else:
        where = ("reading the serial port: usual causes: the wrong device or baud, or the autopilot's port is "
                 "not set to MAVLink 2 (ArduPilot SERIALn_PROTOCOL = 2; PX4 MAV_n_CONFIG)")
    return where + "; also check [vehicle] sysid matches the autopilot's"


class AutopilotWatch:
    def __init__(self, cfg: Config, flight: Supervisor, link: MavlinkLink, report: Reporter,
                 on_position: Callable[[float], None] | None = None,
                 stalled: Callable[[], bool] = lambda: False) -> None:
        self.cfg = cfg
        # True while the companion itself is stalled or just woke from a stall (its loop has
        # not beaten, or the setpoint thread withholds setpoints): what the autopilot did
        # meanwhile is a consequence of that stall, not a pilot's action nor a lost link.
        self.stalled = stalled
        # what the rules remember between readings (companion.autopilot_rules); replaced by _step only
        self.rules = WatchRules.of(cfg)
        self.state = WatchState()
        self._observe: StepObserver = _unobserved
        # PX4's EVENTs, for the last arming-check report (companion.wire.px4_events.arming_report)
        self.events_heard: collections.deque[Note] = collections.deque(maxlen=EVENTS_KEPT)
        self.flight = flight
        self.link = link
        self.report = report
        self.on_position_sample = on_position  # each LOCAL_POSITION_NED, with its arrival time
        self._telemetry_task: asyncio.Task[None] | None = None
        self._events_task: asyncio.Task[bool] | None = None
        self._waiting_said = -math.inf
        self.missing_telemetry: list[str] | None = None  # None: not checked yet
        self.on_link_up: Callable[[str], None] | None = None  # link-up and reconnect (why)

    def connect(self, observe: StepObserver) -> None:
        """Who is shown every call of the rules (the recorder's tap: it must return at once)."""
        self._observe = observe

    # -- telemetry, asked for --------------------------------------------------------------

    def ask_telemetry(self, why: str) -> None:
        """Request the messages the companion uses (on link-up, after a reboot) and check, a
        little later, that each arrives."""
        if self._telemetry_task is not None and not self._telemetry_task.done():
            self._telemetry_task.cancel()
        with contextlib.suppress(RuntimeError):  # no running loop (unit tests)
            self._telemetry_task = asyncio.get_running_loop().create_task(self._ask_telemetry(why))

    async def _ask_telemetry(self, why: str) -> None:
        since = time.monotonic()
        st = self.link.state
        st.position_advice = None
        try:
            answers = await self.link.request_telemetry()
        except OSError as exc:
            log.warning("telemetry request not sent: %s", exc)
            answers = {}
        if st.autopilot == "ardupilot" and st.sw_version is None:
            with contextlib.suppress(CommandFailed, OSError):  # which rate parameters it has
                await self.link.request_version()
        if self.link.state.autopilot == "px4" and self.link.events.metadata is None:
            # PX4's events in words: its metadata over MAVLink FTP (or the cache), meanwhile;
            # before asking for home, which a PX4 not yet ready answers only at its origin
            self._events_task = asyncio.get_running_loop().create_task(self.link.events.load())
        await self._ask_home()
        fleet = bool(self.cfg.fleet.origin) and not self.cfg.fleet.offset_ned
        if fleet:
            await self._ask_origin()
        await asyncio.sleep(max(0.0, since + TELEMETRY_CHECK - time.monotonic()))
        if st.home is None:
            await self._ask_home()
        if fleet and st.gps_origin is None:
            await self._ask_origin()
            if st.gps_origin is None and st.home_lla is None:
                self.report.event("fleet_frame", "fleet frame: cannot place this vehicle yet: the autopilot has "
                                  "reported neither GPS_GLOBAL_ORIGIN nor a HOME_POSITION with a global position "
                                  "(no GPS fix or EKF origin yet; a vehicle without GPS: set [fleet] offset_ned); "
                                  "messages with origin 'fleet' are refused until it does", placed=False)
        missing = self.link.missing_telemetry(since)
        self.missing_telemetry = missing
        if not missing:
            self.report.event("telemetry", f"telemetry arriving ({why}): {', '.join(WANTED)}", missing=[],
                              requested={k: v for k, v in WANTED.items()})
            return
        not_ready = self.px4_not_ready(missing, answers, since)
        waiting = not_ready[0] if not_ready is not None else []
        no_estimate = None if "LOCAL_POSITION_NED" in waiting else self.no_position_estimate(missing, answers, since)
        ignored = [m for m in missing
                   if m not in waiting and not (m == "LOCAL_POSITION_NED" and no_estimate is not None)]
        parts = []
        if not_ready is not None:
            said = (f"PX4 has no estimate yet for {', '.join(waiting)} ({not_ready[1]}): it sends "
                    f"{'them' if len(waiting) > 1 else 'it'} once its estimator is ready (PX4 SIH 1.15: ~37 s "
                    "after boot; \"Ready for takeoff!\", its arming checks pass); nothing to configure")
            if "LOCAL_POSITION_NED" in waiting:
                st.position_advice = said
            parts.append(said)
        if no_estimate is not None:
            st.position_advice = (f"the autopilot has no position estimate yet ({no_estimate}): wait for its EKF "
                                  "origin (a GPS fix, or SET_GPS_GLOBAL_ORIGIN without GPS)")
            parts.append(st.position_advice)
        if ignored:
            hint = self.link.telemetry_hint(ignored)
            said = "; ".join(f"{k}: {v}" for k, v in answers.items() if k in ignored)
            parts.append(f"the autopilot ignores the requests for {', '.join(ignored)}"
                         f"{' (it answered ' + said + ')' if said else ''}: {hint}")
            if "LOCAL_POSITION_NED" in ignored:
                st.position_advice = hint
        msg = (f"the autopilot does not send {', '.join(missing)} ({why}, requested {TELEMETRY_CHECK:.0f} s ago): "
               + "; ".join(parts))
        log.warning("%s", msg)
        self.report.event("telemetry", msg, missing=missing, answers=answers,
                          cause="no_position_estimate" if not ignored else "requests_ignored",
                          hint="; ".join(parts))
        # Say so when it arrives after all (the EKF origin set, a parameter changed).
        while missing:
            await asyncio.sleep(0.25)
            missing = self.link.missing_telemetry(since)
        st.position_advice = None
        self.missing_telemetry = []
        took = time.monotonic() - since
        self.report.event("telemetry", f"telemetry arriving after all ({took:.1f} s after the request): "
                          f"{', '.join(WANTED)}; the advice above "
                          "is withdrawn", missing=[], resolved=True, after_s=round(took, 1))

    def no_position_estimate(self, missing: list[str], answers: dict[str, str], since: float) -> str | None:
        """Why LOCAL_POSITION_NED is missing because the autopilot has no position estimate
        (ArduPilot sends none before its EKF origin is set, even when its interval request was
        accepted), not because it ignores requests: None when nothing says so."""
        if "LOCAL_POSITION_NED" not in missing or "LOCAL_POSITION_NED" in answers:
            return None  # not accepted: that is the request's problem
        st = self.link.state
        signs = ["its interval request was accepted"]
        if any(st.received.get(m, -math.inf) >= since for m in WANTED if m != "LOCAL_POSITION_NED"):
            signs.append("the other requested messages arrive")
        if "GPS_GLOBAL_ORIGIN" not in st.received:
            signs.append("no GPS_GLOBAL_ORIGIN yet")
        if st.home is None:
            signs.append("no HOME_POSITION yet")
        said = [n.text for n in st.notes if ESTIMATE_WORDS.search(n.text)]
        if said:
            signs.append(f"it said {said[-1]!r}")
        return ", ".join(signs) if len(signs) > 1 else None

    def px4_not_ready(self, missing: list[str], answers: dict[str, str],
                      since: float) -> tuple[list[str], str] | None:
        """PX4 sends ATTITUDE and LOCAL_POSITION_NED only once its estimator is ready (real PX4
        SIH 1.15: ATTITUDE 29 s after the link, ~37 s after boot), whatever the interval
        requests say: (the missing ones it explains, the signs), None when nothing says it is
        not ready (home not reported or still at the local origin, where PX4 keeps it until
        ready; its arming checks naming the estimate) or the requests were not accepted."""
        st = self.link.state
        if st.autopilot != "px4":
            return None
        waiting = [m for m in missing if m in PX4_ESTIMATED and m not in answers]
        if not waiting:
            return None
        signs = []
        if st.home_pending:
            signs.append("HOME_POSITION still at the local origin")
        elif st.home is None:
            signs.append("no HOME_POSITION yet")
        said = [n.text for n in (*st.notes, *self.events_heard)
                if ESTIMATE_WORDS.search(n.text) or ESTIMATE_WORDS.search(n.name or "")]
        if said:
            signs.append(f"its arming checks say {said[-1]!r}")
        if not signs:
            return None
        if st.gps_origin is None:
            signs.append("no GPS_GLOBAL_ORIGIN yet")
        head = [f"the interval request{'s were' if len(waiting) > 1 else ' was'} accepted"]
        if any(st.received.get(m, -math.inf) >= since for m in WANTED if m not in waiting):
            head.append("the other requested messages arrive")
        return waiting, ", ".join(head + signs)

    async def _ask_home(self) -> None:
        """HOME_POSITION (origin 'home' messages need it); a refusal is said, not fatal."""
        try:
            await self.link.request_home()
        except (CommandFailed, OSError) as exc:
            log.warning("HOME_POSITION not available: %s", exc)
            self.report.event("telemetry", f"HOME_POSITION not available ({exc}): messages with origin 'home' "
                              "are refused until the autopilot reports it", missing=["HOME_POSITION"])

    async def _ask_origin(self) -> None:
        """GPS_GLOBAL_ORIGIN, which places the vehicle in the fleet frame; a refusal is logged (the
        frame may still come from HOME_POSITION; status `fleet` says whether it is placed)."""
        try:
            await self.link.request_origin()
        except (CommandFailed, OSError) as exc:
            log.warning("GPS_GLOBAL_ORIGIN not available: %s", exc)

    # -- the decisions: companion.autopilot_rules.watch_step, recorded for replay ---------------

    def _step(self, reading: Reading, now: float) -> tuple[Output, ...]:
        """One call of the pure rules: the watch's state replaced, the call shown to the
        observer (the recorder), the supervisor events handed to the supervisor in order and
        what remains returned to the caller, which carries it out."""
        before, flight = self.state, self.flight.value
        self.state, outputs = watch_step(self.rules, before, flight, reading, now)
        # shown before any event is handled: the recorder numbers this step before the
        # transitions it causes, which replay matches to it
        try:
            self._observe(before, flight, reading, now, self.state, outputs)
        except Exception:  # a recorder's fault must never keep an event from the supervisor
            log.exception("autopilot watch: the step observer failed")
        for out in outputs:
            if isinstance(out, WATCH_EVENTS):
                self.flight.handle(out)
            elif isinstance(out, LinkFound | LinkRestored):
                self._link_up(out)
        return outputs

    def _ids(self, msg: Any) -> tuple[int, int]:
        """The message's source; the autopilot's own for a call without a message (the link's
        state is the autopilot's by construction: its peer gate admits nothing else)."""
        if msg is None:
            return self.cfg.vehicle.sysid, self.cfg.vehicle.autopilot_component
        return int(msg.get_srcSystem()), int(msg.get_srcComponent())

    def on_message(self, kind: str, msg: Any) -> None:
        if kind == "HEARTBEAT":
            self.on_heartbeat(msg)
        elif kind == "LOCAL_POSITION_NED":
            now = time.monotonic()
            self.on_position(now, msg)
            if self.on_position_sample is not None:
                self.on_position_sample(now)
        elif kind == "EXTENDED_SYS_STATE":
            self.on_landed_state(int(msg.landed_state), msg)
        elif kind in ("STATUSTEXT", "EVENT"):
            self.on_note(kind, msg)

    def on_note(self, kind: str, msg: Any) -> None:
        """STATUSTEXT (ArduPilot, PX4 before 1.14) and EVENT (PX4 >= 1.14), relayed as `autopilot`."""
        note = self.link.state.notes[-1] if self.link.state.notes else None
        if note is None:
            return
        seq = int(msg.sequence) if kind == "EVENT" else None
        if not self._step(NoteSeen(kind, seq, *self._ids(msg)), time.monotonic()):
            return  # a resent event
        if kind == "STATUSTEXT":
            self.report.event("autopilot", f"autopilot says: {note.text}", source="statustext",
                              severity=int(msg.severity), level=note.level)
            return
        self.events_heard.append(note)  # PX4's arming-check report outlives the link's last 16 notes
        # In words from the autopilot's events metadata (companion.wire.px4_events); without it,
        # the number and why there are no words.
        self.report.event("autopilot", f"autopilot event: {note.text} ({note.level})", source="event",
                          event_id=note.event_id, level=note.level, name=note.name, sequence=seq,
                          text=note.text if note.words else None)

    def on_landed_state(self, landed: int, msg: Any = None) -> None:
        was = self.flight.airborne
        self._step(LandedStateSeen(landed, *self._ids(msg)), time.monotonic())
        if was and not self.flight.airborne:
            self.report.dirty = True

    def on_position(self, now: float, msg: Any = None) -> None:
        """`airborne` from height and speed, while the autopilot sends no landed state."""
        st = self.link.state
        p, v = st.position, st.velocity
        reading = PositionSeen(float(p[0]), float(p[1]), float(p[2]), float(v[0]), float(v[1]), float(v[2]),
                               st.armed, st.last_landed_state, *self._ids(msg))
        if any(isinstance(out, HeightReport) for out in self._step(reading, now)):
            self.report.dirty = True

    def on_heartbeat(self, msg: Any = None) -> None:
        st = self.link.state
        if self._step(HeartbeatSeen(st.autopilot, st.mode, st.armed, self.stalled(), *self._ids(msg),
                                    st.heartbeat_wire), time.monotonic()):
            self.report.dirty = True

    def _link_up(self, out: LinkFound | LinkRestored) -> None:
        """The first heartbeat, or one after the link was lost: said, telemetry asked for, the
        shell told (the autopilot's limits read again)."""
        if isinstance(out, LinkFound):
            self.report.event("link", f"autopilot found: {out.autopilot} in {out.mode}", autopilot=out.autopilot,
                              mode=out.mode)
            self.ask_telemetry("link up")
            if self.on_link_up is not None:
                self.on_link_up("link up")
            return
        self.ask_telemetry("link restored (the autopilot may have rebooted)")
        if self.on_link_up is not None:
            self.on_link_up("link restored")
        self.report.event("link_restored", f"MAVLink link restored after about {out.silence_s:.1f} s without the "
                          f"autopilot (cause: the link): autopilot in {out.mode}, "
                          f"{'armed' if out.armed else 'disarmed'}; send 'start' to take control again",
                          mode=out.mode, armed=out.armed, cause="link", silence_s=round(out.silence_s, 1))

    def check_link(self) -> None:
        if not self.flight.seen_link:
            self._say_waiting()
            return
        st = self.link.state
        self._step(LinkCheck(st.last_heartbeat, st.last_message, self.stalled()), time.monotonic())

    def _say_waiting(self) -> None:
        """No heartbeat yet: said every WAITING_EVERY s (the log; the first time, an event with the hint)."""
        now = time.monotonic()
        if now - self._waiting_said >= WAITING_EVERY:
            first = self._waiting_said == -math.inf
            self._waiting_said = now
            text = f"waiting for autopilot heartbeat on {self.cfg.mavlink.url}"
            hint = waiting_hint(self.cfg.mavlink.url)
            log.warning("%s (%s)", text, hint if first else hint.split(";")[0])
            if first:
                self.report.event("link", f"{text}: {hint}", url=self.cfg.mavlink.url, hint=hint)
