"""The fleet's commit protocol as a pure transition function (issue 24.4; docs/fleet.md).

A vehicle's new plan (a *candidate*) is flown only once *committed*. Between the two it is
*proposed*: published on `<prefix>/<vehicle>/trajectory` with `"commit": "proposed"`, and kept
for `wait` = 2 x `[fleet] max_delay` (the bound on a message's delay between two vehicles).

    (state, event) -> (state, actions)

No clock, no I/O, no trajectories: whether two trajectories conflict (fail to certify the
separation) is decided by the caller (`companion.traffic`) and handed in as a flag. The rules:

- **Ready** (a candidate was planned, against what was known when planning started): it loses at
  once to any conflicting trajectory that is committed, or proposed and still live (first come:
  that proposal may commit before it hears of ours). Otherwise it is proposed and a deadline set.
- **Heard** (another vehicle's trajectory arrived) while proposing: a conflicting committed
  trajectory, or a conflicting proposal of a vehicle that *outranks* us (higher priority, then the
  smaller vehicle id), makes ours lose; a lower-ranked one is ignored (it yields to ours).
  While idle (only our committed trajectory stands): a conflicting committed trajectory of a
  vehicle that outranks us makes us replan (the protocol was broken: a delay over the bound, a
  restart); a lower-ranked one replans itself.
- **Tick** at or after the deadline: commit.

Why two vehicles never both commit conflicting plans: say A outranks B, both candidates conflict.
If one heard the other's proposal before proposing, it yields at Ready and proposes nothing.
Otherwise they proposed less than `max_delay` apart (each had not heard the other), so each
hears the other's proposal before its own deadline (proposal + 2 max_delay): B yields to A, and
A ignores B. A loser replans against the winner's proposal (kept as a neighbour until it is
replaced or expires).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, replace


@dataclass(frozen=True)
class Rank:
    """Who wins a tie: the higher priority, then the smaller vehicle id."""

    priority: int
    vehicle: str

    def outranks(self, other: Rank) -> bool:
        if self.priority != other.priority:
            return self.priority > other.priority
        return self.vehicle < other.vehicle


class Phase(enum.Enum):
    IDLE = "idle"  # nothing proposed: our committed trajectory (if any) stands
    PROPOSED = "proposed"  # a candidate waits for its deadline


@dataclass(frozen=True)
class State:
    me: Rank
    wait: float  # s: 2 x [fleet] max_delay
    phase: Phase = Phase.IDLE
    seq: int = 0  # the candidate's number (each Ready has its own)
    deadline: float = 0.0


@dataclass(frozen=True)
class Other:
    """A trajectory of another vehicle, as far as the protocol needs it."""

    rank: Rank
    committed: bool  # committed (flown), else proposed
    conflicts: bool  # does not certify against our candidate (Ready, Heard while proposing)
    conflicts_committed: bool = False  # does not certify against our committed trajectory (Heard)


@dataclass(frozen=True)
class Ready:
    seq: int
    now: float
    known: tuple[Other, ...]  # every other vehicle's live trajectories when the candidate is ready


@dataclass(frozen=True)
class Heard:
    now: float
    other: Other


@dataclass(frozen=True)
class Tick:
    now: float


@dataclass(frozen=True)
class Cancel:
    """The candidate is given up by its owner (the flown plan changed, control ended)."""


Event = Ready | Heard | Tick | Cancel


@dataclass(frozen=True)
class Propose:
    seq: int
    deadline: float


@dataclass(frozen=True)
class Commit:
    seq: int


@dataclass(frozen=True)
class Lose:
    """The candidate `seq` is not flown: replan against `winner`'s trajectory."""

    seq: int
    winner: str
    reason: str


@dataclass(frozen=True)
class Replan:
    """Our committed trajectory conflicts with `winner`'s, which outranks us: replan."""

    winner: str
    reason: str


Action = Propose | Commit | Lose | Replan


def _why(o: Other) -> str:
    return "committed" if o.committed else "proposed"


def step(state: State, event: Event) -> tuple[State, list[Action]]:
    """One transition (module docstring)."""
    if isinstance(event, Ready):
        blocking = [o for o in event.known if o.conflicts]
        if blocking:
            o = min(blocking, key=lambda o: (not o.committed, o.rank.vehicle))
            return replace(state, phase=Phase.IDLE, seq=event.seq), [
                Lose(event.seq, o.rank.vehicle, f"conflicts with {o.rank.vehicle}'s {_why(o)} trajectory")]
        deadline = event.now + state.wait
        return replace(state, phase=Phase.PROPOSED, seq=event.seq, deadline=deadline), [Propose(event.seq, deadline)]
    if isinstance(event, Heard):
        o = event.other
        if o.rank.vehicle == state.me.vehicle:
            return state, []
        if state.phase is Phase.PROPOSED:
            if o.conflicts and (o.committed or o.rank.outranks(state.me)):
                why = ("committed" if o.committed else f"proposed, and it outranks us (priority {o.rank.priority} "
                       f"against {state.me.priority}, then vehicle id)")
                return replace(state, phase=Phase.IDLE), [
                    Lose(state.seq, o.rank.vehicle, f"{o.rank.vehicle} {why} a conflicting trajectory meanwhile")]
            return state, []
        if o.committed and o.conflicts_committed and o.rank.outranks(state.me):
            return state, [Replan(o.rank.vehicle, f"{o.rank.vehicle} committed a trajectory conflicting with ours "
                                                  "and outranks us")]
        return state, []
    if isinstance(event, Tick):
        if state.phase is Phase.PROPOSED and event.now >= state.deadline:
            return replace(state, phase=Phase.IDLE), [Commit(state.seq)]
        return state, []
    return replace(state, phase=Phase.IDLE), []
