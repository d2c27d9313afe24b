"""The tracking error's rules (companion.tracking_rules.tracking_step), on their own: the brake
after exactly TRACKING_SAMPLES samples over the limit in a row, once per excursion, never while
the last tracking stop runs, never unless a plan of ours is flown and a limit is set; the margin
warning at exactly its RMS and max shares; and the same decisions, sample for sample, as the
mutable checks of companion/tracking.py they replaced (kept here as the oracle)."""

from __future__ import annotations

import collections
import math
from dataclasses import replace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.tracking_rules import (
    BRAKE_REASON,
    TRACKING_MAX_SHARE,
    TRACKING_RMS_SHARE,
    TRACKING_SAMPLES,
    TRACKING_WINDOW,
    Brake,
    MarginEvent,
    Output,
    StateSeen,
    TrackingEvent,
    TrackingRules,
    TrackingSample,
    TrackingState,
    tracking_step,
)

RULES = TrackingRules()
LIMITS = st.sampled_from([0.125, 0.25, 0.5, 1.0, 2.0])  # powers of two: the shares of them are exact


def sample(error: float | None, limit: float = 1.0, *, ours: bool = True, flying: bool = True,
           running: bool = False) -> TrackingSample:
    return TrackingSample(error, ours, flying, limit, "[planner] tracking_allowance", limit, running)


def run(readings: list[TrackingSample], rules: TrackingRules = RULES,
        state: TrackingState | None = None) -> list[tuple[Output, ...]]:
    ts = state or TrackingState()
    outs = []
    for r in readings:
        ts, out = tracking_step(rules, ts, r)
        outs.append(out)
    return outs


def kinds(out: tuple[Output, ...]) -> list[type]:
    return [type(o) for o in out]


@given(st.lists(st.booleans(), max_size=60), LIMITS)
@settings(max_examples=200, deadline=None)
def test_a_brake_comes_at_the_samples_th_sample_of_each_excursion_and_only_then(over: list[bool],
                                                                               limit: float) -> None:
    # errors well under the margin shares when under, just over the limit when over
    readings = [sample(limit * (1.01 if o else 0.01), limit) for o in over]
    outs = run(readings, replace(RULES, window=10**6))  # no margin warning in the way
    for i, out in enumerate(outs):
        excursion_starts = next(k for k in range(i, -2, -1) if k < 0 or not over[k]) + 1
        nth = i - excursion_starts + 1  # this sample's place in its run over the limit (0: under)
        want = [TrackingEvent, Brake] if over[i] and nth == TRACKING_SAMPLES else []
        assert kinds(out) == want, (i, over)
        if want:
            event, brake = out
            assert isinstance(event, TrackingEvent) and isinstance(brake, Brake)
            assert event.samples == TRACKING_SAMPLES and event.flying and event.error == readings[i].error
            assert brake.reason == f"{BRAKE_REASON}{event.error:.2f} m > [planner] tracking_allowance {limit:.2f} m"


def test_one_over_the_limit_for_longer_brakes_once_and_once_more_after_coming_back() -> None:
    outs = run([sample(2.0)] * 20 + [sample(0.1)] + [sample(2.0)] * 5)
    braked = [i for i, out in enumerate(outs) if Brake in kinds(out)]
    assert braked == [TRACKING_SAMPLES - 1, 20 + TRACKING_SAMPLES]


def test_the_limit_itself_is_not_over_it() -> None:
    assert not any(run([sample(1.0)] * 10, replace(RULES, window=10**6)))
    assert Brake in kinds(run([sample(math.nextafter(1.0, 2.0))] * TRACKING_SAMPLES)[-1])


@given(st.lists(st.tuples(st.floats(0.0, 10.0), st.booleans(), st.booleans()), max_size=40), LIMITS)
@settings(max_examples=200, deadline=None)
def test_nothing_is_said_nor_remembered_unless_a_plan_of_ours_is_flown_with_a_limit(
        seen: list[tuple[float, bool, bool]], limit: float) -> None:
    """Not flying ours, or no error measured: nothing said, the count and the window forgotten
    (the `said` of the excursion is kept); a limit <= 0: nothing at all, the state untouched."""
    busy = TrackingState(over=2, said=True, nearing_said=True, errors=(0.5,) * 60)
    for error, ours, measured in seen:
        r = sample(error if measured else None, limit, ours=ours)
        if ours and measured:
            continue
        ts, out = tracking_step(RULES, busy, r)
        assert out == () and ts == TrackingState(said=True)
    for error, _ours, _m in seen:
        for off in (0.0, -limit):
            ts, out = tracking_step(RULES, busy, sample(error, off))
            assert out == () and ts is busy


@given(st.integers(TRACKING_SAMPLES, 12), st.integers(0, 8))
@settings(max_examples=100, deadline=None)
def test_nothing_while_the_last_tracking_stop_runs_and_the_count_goes_on(running_for: int, after: int) -> None:
    """The stop still running through the samples-th sample: the event waits for it to end and
    then says the samples counted all along; a stop running through the whole excursion: nothing."""
    readings = [sample(3.0, running=k < running_for) for k in range(running_for + after)]
    outs = run(readings)
    for k, out in enumerate(outs[:running_for]):
        assert out == (), k
    said = [(k, out) for k, out in enumerate(outs) if out]
    if after == 0:
        assert said == []
    else:
        ((k, (event, brake)),) = said
        assert k == running_for and isinstance(event, TrackingEvent) and event.samples == running_for + 1
        assert isinstance(brake, Brake)


def test_holding_already_says_so_and_does_not_brake() -> None:
    *_, out = run([sample(3.0, flying=False)] * TRACKING_SAMPLES)
    (event,) = out
    assert isinstance(event, TrackingEvent) and not event.flying
    assert event.message().endswith(f"for {TRACKING_SAMPLES} samples: holding already")


@given(LIMITS, st.integers(TRACKING_WINDOW // 3, TRACKING_WINDOW))
@settings(max_examples=60, deadline=None)
def test_the_margin_warning_comes_at_exactly_the_rms_share(limit: float, n: int) -> None:
    """`n` errors of exactly the RMS share of the limit (their RMS is that exactly): warned at
    the window's third, not before; just under it (one error of 0): not warned."""
    at = TRACKING_RMS_SHARE * limit
    outs = run([sample(at, limit)] * n)
    assert [i for i, out in enumerate(outs) if out] == [TRACKING_WINDOW // 3 - 1]
    (warning,) = outs[TRACKING_WINDOW // 3 - 1]
    assert isinstance(warning, MarginEvent) and warning.rms == at and warning.worst == at
    assert warning.samples == TRACKING_WINDOW // 3
    assert not any(run([sample(0.0, limit)] + [sample(at, limit)] * (TRACKING_WINDOW // 3 - 1)))


@given(LIMITS, st.integers(0, TRACKING_WINDOW // 3 - 1))
@settings(max_examples=60, deadline=None)
def test_the_margin_warning_comes_at_exactly_the_max_share(limit: float, where: int) -> None:
    at = TRACKING_MAX_SHARE * limit
    for worst, warned in ((at, True), (math.nextafter(at, 0.0), False)):
        errors = [0.0] * (TRACKING_WINDOW // 3)
        errors[where] = worst
        *_, last = run([sample(e, limit) for e in errors])
        assert (kinds(last) == [MarginEvent]) is warned, (worst, warned)


def test_the_margin_warning_is_said_once_per_flight_phase() -> None:
    phase = [sample(0.6)] * TRACKING_WINDOW
    outs = run([*phase, sample(0.6, ours=False), *phase])
    warned = [i for i, out in enumerate(outs) if out]
    assert warned == [TRACKING_WINDOW // 3 - 1, TRACKING_WINDOW + TRACKING_WINDOW // 3]


def test_the_warning_names_the_brake_when_it_is_set_apart() -> None:
    *_, out = run([sample(0.9)] * (TRACKING_WINDOW // 3), replace(RULES, brake_apart=True))
    (warning,) = out
    assert isinstance(warning, MarginEvent) and "near the brake" in warning.message()
    assert "is what the obstacles are inflated by" in warning.message()


def test_a_recorded_state_is_its_window_by_length_and_digest() -> None:
    a = TrackingState(errors=(0.1, 0.2))
    assert StateSeen.of(a) == StateSeen.of(TrackingState(errors=(0.1, 0.2)))
    assert StateSeen.of(a).digest != StateSeen.of(TrackingState(errors=(0.1, math.nextafter(0.2, 1.0)))).digest


# -- the oracle: companion/tracking.py's checks before they became tracking_step --------------


class Before:
    def __init__(self) -> None:
        self.over, self.said, self.nearing = 0, False, False
        self.recent: collections.deque[float] = collections.deque(maxlen=TRACKING_WINDOW)

    def check(self, r: TrackingSample) -> list[tuple[str, object]]:
        said: list[tuple[str, object]] = []
        if r.error is None or not r.flying_ours:
            self.over, self.nearing = 0, False
            self.recent.clear()
            return said
        err, limit = r.error, r.limit
        if limit <= 0.0:
            return said
        self.recent.append(err)
        if not self.nearing and len(self.recent) >= TRACKING_WINDOW // 3:
            e = np.asarray(self.recent)
            rms, worst = float(np.sqrt(np.mean(e * e))), float(e.max())
            if not (rms < TRACKING_RMS_SHARE * limit and worst < TRACKING_MAX_SHARE * limit):
                self.nearing = True
                said.append(("tracking_margin", (rms, worst, len(e))))
        self.over = self.over + 1 if err > limit else 0
        if self.over == 0:
            self.said = False
            return said
        if self.over < TRACKING_SAMPLES or self.said or r.stop_running:
            return said
        self.said = True
        said.append(("tracking", (err, self.over)))
        if r.flying:
            said.append(("hold", f"tracking error {err:.2f} m > {r.limit_name} {limit:.2f} m"))
        return said


def said_now(out: tuple[Output, ...]) -> list[tuple[str, object]]:
    def one(o: Output) -> tuple[str, object]:
        if isinstance(o, MarginEvent):
            return "tracking_margin", (o.rms, o.worst, o.samples)
        if isinstance(o, TrackingEvent):
            return "tracking", (o.error, o.samples)
        return "hold", o.reason
    return [one(o) for o in out]


READINGS = st.builds(sample, st.one_of(st.none(), st.floats(0.0, 1.5)), st.sampled_from([1.0, 0.0, 0.3]),
                     ours=st.sampled_from([True, True, True, False]), flying=st.booleans(),
                     running=st.booleans())


@given(st.lists(READINGS, min_size=1, max_size=400))
@settings(max_examples=150, deadline=None)
def test_the_same_decisions_as_the_checks_it_replaced(readings: list[TrackingSample]) -> None:
    old, ts = Before(), TrackingState()
    for r in readings:
        ts, out = tracking_step(RULES, ts, r)
        assert said_now(out) == old.check(r)
        assert (ts.over, ts.said, ts.nearing_said, ts.errors) == (old.over, old.said, old.nearing, tuple(old.recent))
