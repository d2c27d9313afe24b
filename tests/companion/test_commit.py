"""The fleet's commit protocol as a pure function (companion.commit): tie-break, first come,
and a randomised two-vehicle race with every message delayed by up to the bound."""

from __future__ import annotations

import heapq
import random

from companion.commit import (
    Cancel,
    Commit,
    Heard,
    Lose,
    Other,
    Phase,
    Propose,
    Rank,
    Ready,
    Replan,
    State,
    Tick,
    step,
)

A, B = Rank(0, "drone1"), Rank(0, "drone2")


def test_rank_priority_then_vehicle_id() -> None:
    assert A.outranks(B) and not B.outranks(A)
    assert Rank(2, "zulu").outranks(Rank(1, "alpha"))
    assert not Rank(1, "alpha").outranks(Rank(1, "alpha"))


def test_a_free_candidate_is_proposed_then_committed_at_its_deadline() -> None:
    s, acts = step(State(A, wait=0.2), Ready(1, 10.0, (Other(B, True, False),)))
    assert acts == [Propose(1, 10.2)] and s.phase is Phase.PROPOSED
    s, acts = step(s, Tick(10.1))
    assert acts == []
    s, acts = step(s, Tick(10.2))
    assert acts == [Commit(1)] and s.phase is Phase.IDLE


def test_a_candidate_loses_at_once_to_a_conflicting_committed_or_live_proposal() -> None:
    for committed in (True, False):
        s, acts = step(State(A, 0.2), Ready(3, 0.0, (Other(B, committed, True),)))
        assert len(acts) == 1 and isinstance(acts[0], Lose) and acts[0].winner == "drone2" and acts[0].seq == 3
        assert s.phase is Phase.IDLE


def test_while_proposed_the_higher_rank_wins() -> None:
    s, _ = step(State(B, 0.2), Ready(1, 0.0, ()))
    s2, acts = step(s, Heard(0.1, Other(A, False, True)))
    assert isinstance(acts[0], Lose) and s2.phase is Phase.IDLE
    assert step(s2, Tick(1.0))[1] == []  # a lost candidate is never committed
    s, _ = step(State(A, 0.2), Ready(1, 0.0, ()))
    s, acts = step(s, Heard(0.1, Other(B, False, True)))
    assert acts == [] and s.phase is Phase.PROPOSED
    assert step(s, Tick(0.2))[1] == [Commit(1)]
    # a conflicting commit beats any rank; a trajectory that does not conflict changes nothing
    s, _ = step(State(A, 0.2), Ready(1, 0.0, ()))
    assert isinstance(step(s, Heard(0.1, Other(B, True, True)))[1][0], Lose)
    assert step(s, Heard(0.1, Other(Rank(9, "x"), False, False)))[1] == []


def test_idle_a_conflicting_commit_of_a_higher_rank_makes_us_replan() -> None:
    s = State(B, 0.2)
    _, acts = step(s, Heard(0.0, Other(A, True, False, conflicts_committed=True)))
    assert isinstance(acts[0], Replan) and acts[0].winner == "drone1"
    assert step(State(A, 0.2), Heard(0.0, Other(B, True, False, conflicts_committed=True)))[1] == []
    assert step(s, Heard(0.0, Other(A, False, False, conflicts_committed=True)))[1] == []


def test_cancel_drops_the_candidate() -> None:
    s, _ = step(State(A, 0.2), Ready(1, 0.0, ()))
    s, _ = step(s, Cancel())
    assert step(s, Tick(5.0))[1] == []


def test_two_vehicles_racing_never_both_commit_conflicting_candidates() -> None:
    """Each proposes at a random time; each proposal reaches the other after a random delay up to
    the bound; each yields at Ready to a proposal already heard. Never both commit; whenever one
    did not hear the other before proposing, exactly one commits."""
    rng = random.Random(7)
    bound = 0.1
    for _ in range(3000):
        ranks = [Rank(rng.choice([0, 0, 1]), "drone1"), Rank(rng.choice([0, 0, 1]), "drone2")]
        delay = [rng.uniform(0.0, bound), rng.uniform(0.0, bound)]
        states = [State(r, 2 * bound) for r in ranks]
        # (time, order, vehicle, what): deliveries before ticks at the same instant
        queue: list[tuple[float, int, int, str]] = [(rng.uniform(0.0, 0.3), 2, i, "ready") for i in (0, 1)]
        heapq.heapify(queue)
        committed = [False, False]
        proposed = [False, False]
        heard = [False, False]  # i heard the other's proposal
        while queue:
            t, _, i, what = heapq.heappop(queue)
            if what == "ready":
                known = (Other(ranks[1 - i], False, True),) if heard[i] else ()
                states[i], acts = step(states[i], Ready(1, t, known))
            elif what == "deliver":
                heard[i] = True
                states[i], acts = step(states[i], Heard(t, Other(ranks[1 - i], False, True)))
            else:
                states[i], acts = step(states[i], Tick(t))
            for a in acts:
                if isinstance(a, Propose):
                    proposed[i] = True
                    heapq.heappush(queue, (t + delay[i], 0, 1 - i, "deliver"))
                    heapq.heappush(queue, (a.deadline, 1, i, "tick"))
                elif isinstance(a, Commit):
                    committed[i] = True
        assert not all(committed), (ranks, delay)
        if all(proposed):
            assert any(committed), (ranks, delay)
