"""The fleet's separation on the loop: what the others fly, and committing ours (issue 24.3-4).

The shell around `companion.traffic` (the others' trajectories) and `companion.commit` (the
protocol as a pure function): it reads the others' trajectory messages and liveliness, hands
planning the `Neighbours` to keep away from, runs a candidate plan through propose / wait /
commit, and adds the `fleet` object to every trajectory message we publish. Off (every method a
no-op, nothing published differently) without `[fleet] origin` or with `[fleet] separation = 0`.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections.abc import Callable
from typing import Any

from companion import commit as cp
from companion.clocks import ClockCheck
from companion.config import Config
from companion.fleet import FleetFrame
from companion.geodesy import Placement
from companion.traffic import Claim, Traffic, named_neighbours, other, read_claim, to_fleet
from planner_core import Bounds, Trajectory
from planner_core.separation import Neighbours, SeparationCertificate, bound_speed, speed_bound

log = logging.getLogger("companion")

REPUBLISH = 1.0  # s: the committed trajectory is published again this often (late joiners, lost puts)


class Deconfliction:
    def __init__(self, cfg: Config, frame: FleetFrame, t_base: Callable[[], float | None],
                 publish: Callable[[bytes], None], event: Callable[..., None]) -> None:
        self.cfg = cfg
        self.frame = frame
        self.enabled = frame.enabled and cfg.fleet.separation > 0.0
        self._t_base = t_base  # the flight's time base (monotonic s at trajectory time 0), None when not flying
        self.publish_bytes = publish  # a proposal, as bytes, on our trajectory key
        self.event = event  # Reporter.event
        self.traffic = Traffic(cfg.vehicle.id)
        self.me = cp.Rank(cfg.fleet.priority, cfg.vehicle.id)
        self.wait = 2.0 * cfg.fleet.max_delay
        self.state = cp.State(self.me, self.wait)
        # shown every call of the protocol's rule (the flight recorder's tap: it must return at once)
        self.observe: Callable[[cp.State, cp.Event, cp.State, tuple[cp.Action, ...]], None] = \
            lambda _b, _e, _a, _x: None
        # shown every sample of the clock check and its verdict (vehicle, sent, arrived, why off)
        self.observe_clock: Callable[[str, float, float, str | None], None] = lambda _v, _s, _a, _w: None
        self.seq = 0
        self.committed_seq = 0
        # the candidate that won (its number and certificates), until it is published as committed
        self.approved: tuple[int, dict[str, Any]] | None = None
        self.proposed: Trajectory | None = None  # the candidate proposed (local, flight time)
        self._lost: asyncio.Future[str] | None = None
        self.ours: Trajectory | None = None  # our committed trajectory, fleet frame
        self.on_replan: Callable[[str], None] = lambda _why: None  # a higher-ranked vehicle's commit conflicts
        self.replans = 0  # deconfliction replans (a lost candidate, a conflicting commit)
        self.speed = math.inf
        self._mono_base: float | None = None
        self.order: list[str] = []  # the vehicles of the last Neighbours handed out, in order
        self._wall_base = 0.0
        self.certificates_verified = 0  # the others' certificates against our committed trajectory
        self.certificates_refused = 0
        # our system clock against the others' (companion.clocks): while it is off, nothing that
        # depends on the others is committed, and a mission flying is stopped (on_clock_off)
        self.clocks = ClockCheck(cfg.fleet.clock_tolerance, cfg.fleet.max_delay)
        self.clock_off: str | None = None
        self.on_clock_off: Callable[[str], None] = lambda _why: None

    # -- time and frame ---------------------------------------------------------------

    def time_base(self) -> float | None:
        """The system-clock time of flight time 0 (None when not flying)."""
        tb = self._t_base()
        if tb is None:
            return None
        if tb != self._mono_base:  # once per time base: every message of a flight says the same
            self._mono_base, self._wall_base = tb, tb + (time.time() - time.monotonic())
        return self._wall_base

    def placement(self) -> Placement | None:
        return self.frame.placement

    def why_not(self) -> str | None:
        """Why plans that depend on the others cannot be made now (None when they can)."""
        if not self.enabled:
            return None
        if self.placement() is None:
            return f"the fleet frame is not placed ({self.frame.reason}): cannot plan against the other vehicles"
        if self.time_base() is None:
            return "no flight time base yet"
        return None

    # -- planning ------------------------------------------------------------------------

    def neighbours(self, bounds: Bounds | None = None) -> Neighbours | None:
        """The others' live trajectories for the planner (local frame, flight time)."""
        if not self.enabled or self.why_not() is not None:
            return None
        if bounds is not None:
            self.speed = bound_speed(bounds)
        pl, tb = self.placement(), self.time_base()
        assert pl is not None and tb is not None
        got = self.traffic.neighbours(pl, tb, self.cfg.fleet.separation, self.cfg.fleet.clock_tolerance, time.time())
        if got is None:
            return None
        nb, claims = got
        self.order = [c.vehicle for c in claims]  # planner_core's "neighbour k" is self.order[k]
        return nb if math.isinf(self.speed) else Neighbours(nb.trajectories, nb.separation, nb.clock_tolerance,
                                                             speed=self.speed, speeds=nb.speeds, reach=nb.reach)

    def named(self, text: str) -> str:
        """planner_core's "neighbour k" in a message as the vehicle it is."""
        return named_neighbours(text, self.order)

    def names(self) -> list[str]:
        return sorted({c.vehicle for c in self.traffic.live(time.time())})

    def _check(self, ours: Trajectory, only: list[Claim] | None = None) -> list[tuple[Claim, SeparationCertificate | None, str]]:
        pl, tb = self.placement(), self.time_base()
        assert pl is not None and tb is not None
        # the bound speed we state: the bounds', and never below the trajectory's own (a takeoff, a stop)
        speed = max(self.speed if math.isfinite(self.speed) else 0.0, speed_bound(ours))
        return self.traffic.check(ours, pl, tb, self.cfg.fleet.separation, self.cfg.fleet.clock_tolerance, speed,
                                  time.time(), only)

    # -- the commit protocol ---------------------------------------------------------------

    def _step(self, event: cp.Event) -> list[cp.Action]:
        """One call of the protocol's rule (companion.commit.step), the state replaced and the
        call shown to the recorder (/fleet/commit), which replay runs again."""
        before = self.state
        self.state, acts = cp.step(before, event)
        try:
            self.observe(before, event, self.state, tuple(acts))
        except Exception:  # a recorder's fault must never change what the fleet decides
            log.exception("fleet: the commit observer failed")
        return acts

    async def commit(self, candidate: Trajectory, what: str) -> str | None:
        """Propose `candidate` (local, flight time), wait, commit: None when it may be flown (the
        caller swaps it in at once), else why it lost (replan against the winner)."""
        if not self.enabled:
            return None
        why = self.why_not() or self.clock_off
        if why is not None:
            return why
        self.seq += 1
        seq = self.seq
        checks = self._check(candidate)
        known = tuple(other(c, cert is None) for c, cert, _ in checks)
        acts = self._step(cp.Ready(seq, time.monotonic(), known))
        log.info("fleet: candidate %d for %s against %s: %s", seq, what,
                 [(c.vehicle, c.seq, c.committed, cert is not None) for c, cert, _ in checks], acts)
        for a in acts:
            if isinstance(a, cp.Lose):
                self.replans += 1
                bad = [m for c, cert, m in checks if cert is None and c.vehicle == a.winner]
                return f"{what}: {a.reason}" + (f" ({bad[0]})" if bad else "")
        # Traffic.check certifies in the fleet frame on the system clock: what a receiver checks
        certs = {c.vehicle: {"seq": c.seq, "certificate": cert.to_dict()} for c, cert, _ in checks if cert is not None}
        self.proposed = candidate
        loop = asyncio.get_running_loop()
        lost: asyncio.Future[str] = loop.create_future()
        self._lost = lost
        body = self.section("proposed", seq, certs, expires=time.time() + self.wait + self.cfg.fleet.max_delay)
        self.publish_bytes(self._encode(candidate, body))
        try:
            await asyncio.wait([lost], timeout=self.wait)
            if lost.done():
                self.replans += 1
                return f"{what}: {lost.result()}"
            acts = self._step(cp.Tick(time.monotonic()))
            if any(isinstance(a, cp.Commit) and a.seq == seq for a in acts):
                self.approved = (seq, certs)  # published as committed when swapped in (committed_section)
                return None
            self.replans += 1
            return f"{what}: the proposal was given up"
        finally:
            self.proposed = None
            self._lost = None

    def cancel(self) -> None:
        self.approved = None
        self._step(cp.Cancel())

    # -- what we publish ------------------------------------------------------------------

    def section(self, commit: str, seq: int, certs: dict[str, Any], expires: float | None = None,
                radius: float = 0.0) -> dict[str, Any]:
        pl, tb = self.placement(), self.time_base()
        return {
            "commit": commit, "seq": seq, "vehicle": self.cfg.vehicle.id, "priority": self.cfg.fleet.priority,
            "time_base": tb, "frame": "fleet-ned", "offset_ned": None if pl is None else pl.offset.tolist(),
            "rotation": None if pl is None else pl.rotation.tolist(),
            "radius": radius or self.cfg.planner.vehicle_radius,
            "bound_speed": self.speed if math.isfinite(self.speed) else None,
            "separation": self.cfg.fleet.separation, "clock_tolerance": self.cfg.fleet.clock_tolerance,
            "expires": expires, "certificates": certs,
        }

    def committed_section(self, traj: Trajectory) -> dict[str, Any] | None:
        """The `fleet` object of a committed plan's message (None when off or not placed): a
        plan swapped in after `commit` carries that commit's certificates; a hold or a stop the
        next sequence number and none."""
        if not self.enabled or self.why_not() is not None:
            return None
        approved, self.approved = self.approved, None
        if approved is not None and approved[0] == self.seq:
            self.committed_seq, certs = approved
        else:  # a hold, a stop, a takeoff: not through the protocol (docs/fleet.md); certified when it can be
            self.seq += 1
            self.committed_seq, certs = self.seq, {}
            if self.traffic.committed or self.traffic.proposed:
                checks = self._check(traj)
                certs = {c.vehicle: {"seq": c.seq, "certificate": cert.to_dict()} for c, cert, _ in checks
                         if cert is not None}
                bad = [f"{c.vehicle} ({m})" for c, cert, m in checks if cert is None]
                if bad:
                    self.event("fleet", "the trajectory flown now (a hold, a stop or a takeoff, which do not wait for "
                               f"the protocol) is not certified separated from {'; '.join(bad)}")
        pl, tb = self.placement(), self.time_base()
        assert pl is not None and tb is not None
        self.ours = to_fleet(traj, pl, tb)
        return self.section("committed", self.committed_seq, certs)

    @staticmethod
    def _encode(traj: Trajectory, fleet: dict[str, Any]) -> bytes:
        from companion.wire.encode import encode_trajectory

        return encode_trajectory(traj, fleet)

    # -- what we hear -----------------------------------------------------------------------

    def on_trajectory(self, vehicle: str, payload: bytes, sent: float | None = None,
                      arrived: float | None = None) -> None:
        """Another vehicle's trajectory message (on the loop); `sent`: its send time on its clock
        (the put's attachment), `arrived`: ours when it arrived (system clock)."""
        if not self.enabled or vehicle == self.cfg.vehicle.id:
            return
        try:
            body = json.loads(payload)
        except ValueError:
            return
        claim = read_claim(body, vehicle) if isinstance(body, dict) else None
        if claim is None:
            return
        if sent is not None and arrived is not None:  # a vehicle's trajectory (the router checked who may put it)
            self.clocks.heard(vehicle, sent, arrived)
            self._clock_verdict(arrived)
            try:
                self.observe_clock(vehicle, sent, arrived, self.clock_off)
            except Exception:  # a recorder's fault must never change what the fleet decides
                log.exception("fleet: the clock observer failed")
        held = (self.traffic.committed if claim.committed else self.traffic.proposed).get(vehicle)
        if held is not None and held.seq == claim.seq:
            return  # the same trajectory published again (REPUBLISH)
        if not self.traffic.heard(claim):
            return
        log.info("fleet: heard %s %s seq %d (pending %s, phase %s)", vehicle,
                 "committed" if claim.committed else "proposed", claim.seq, self.proposed is not None,
                 self.state.phase.value)
        bad = self.traffic.verify_theirs(claim, self.ours, self.committed_seq)
        if bad is not None:
            self.certificates_refused += 1
            self.event("fleet", f"separation certificate refused: {bad}", vehicle_other=vehicle)
        elif self.ours is not None and self.cfg.vehicle.id in claim.certificates:
            self.certificates_verified += 1
        if self.why_not() is not None:
            return
        if self.proposed is not None and self._lost is not None and not self._lost.done():
            (_, cert, msg), = self._check(self.proposed, [claim])
            acts = self._step(cp.Heard(time.monotonic(), other(claim, cert is None)))
            for a in acts:
                if isinstance(a, cp.Lose):
                    self._lost.set_result(a.reason + (f" ({msg})" if msg else ""))
        elif claim.committed and self.ours is not None and claim.rank.outranks(self.me):
            pl, tb = self.placement(), self.time_base()
            assert pl is not None and tb is not None
            from companion.traffic import to_local

            (_, cert, msg), = self._check(to_local(self.ours, pl, tb), [claim])
            acts = self._step(cp.Heard(time.monotonic(), other(claim, False, conflicts_committed=cert is None)))
            for a in acts:
                if isinstance(a, cp.Replan):
                    self.replans += 1
                    self.on_replan(f"{a.reason} ({msg})")

    def _clock_verdict(self, now: float) -> None:
        why, was = self.clocks.ours_off(now), self.clock_off
        self.clock_off = why
        if (why is None) == (was is None):  # no news (the reason's figures may have moved)
            return
        if why is not None:
            self.event("fleet", f"{why}: plans that depend on the other vehicles are refused until it agrees again "
                       "(a mission flying is stopped); check NTP/chrony on this computer", clock_off=True)
            self.on_clock_off(why)
        else:
            self.event("fleet", "our system clock agrees with the fleet's again: plans are made against the other "
                       "vehicles again", clock_off=False)

    def on_alive(self, vehicle: str, alive: bool) -> None:
        if not self.enabled or vehicle == self.cfg.vehicle.id:
            return
        self.traffic.liveliness(vehicle, alive, time.time())
        if not alive and vehicle in self.traffic.committed:
            self.event("fleet", f"{vehicle} is silent (liveliness lost): its last trajectory and final hold stay "
                       "reserved, widened by how far it could have gone since", vehicle_other=vehicle)

    def status(self) -> dict[str, Any] | None:
        if not self.enabled:
            return None
        now = time.time()
        return {"neighbours": self.names(), "lost": self.traffic.lost(), "replans": self.replans,
                "certificates_verified": self.certificates_verified, "certificates_refused": self.certificates_refused,
                "widening_m": {v: round(self.traffic.widening(v, now), 2) for v in self.traffic.lost()},
                "separation": self.cfg.fleet.separation, "priority": self.cfg.fleet.priority,
                "clock_off": self.clock_off,
                "clock_offsets_ms": {v: [round(o.lo * 1000, 1), round(o.hi * 1000, 1)]
                                     for v, o in sorted(self.clocks.offsets(now).items())},
                "clocks_disagreeing": self.clocks.others_off(now)}
