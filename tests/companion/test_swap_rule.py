"""The swap's rule (companion.control.swap_refusal) on stops: a verified stop starts exactly where
the flown plan is (its first jet is pinned), so it is swapped in however short its leading
segment; a plan that starts from another state, by a little in any derivative, is refused."""

from __future__ import annotations

import numpy as np

from companion.braking import _jet_at
from companion.control import SWAP_JETS, swap_refusal
from planner_core import Bounds, Trajectory, sampler, splice
from planner_core.braking import braking_trajectory
from tests.companion.test_route import fly

WIDE = Bounds.symmetric(50.0, 50.0, 500.0, 5000.0)  # the stop's own bounds: never the reason here


def _flown() -> Trajectory:
    # 25-55 m from the origin: rounding grows with the control points' size
    return fly([[30.0, 0.0, -1.5], [30.0, 25.0, -1.5]], [25.0, 0.0, -1.5], t0=0.0).trajectory


def test_a_stop_with_a_short_leading_segment_is_swapped_in() -> None:
    base = _flown()
    checked = old_rule_refused = 0
    for t_b in np.linspace(base.t0 + 0.5, base.t_end - 0.5, 40):
        jet = _jet_at(base, float(t_b))
        for d in (0.4, 0.8, 1.6):  # leading segments of 32 ms to 0.4 s (braking's LEADS 0.08 / 0.25)
            stop = braking_trajectory(jet, WIDE, None, float(t_b), durations=[d]).trajectory
            if stop is None:
                continue
            new = splice(base, stop)
            checked += 1
            assert swap_refusal(base, new, float(t_b) - 0.3, 0.0, 50.0, float(t_b)) == "", (t_b, d)
            # what the rule did before (1e-6 on every derivative): snap rounds by ~1e-5 there
            old_rule_refused += not np.allclose(sampler(base).jet(float(t_b)), sampler(new).jet(float(t_b)),
                                                rtol=1e-6, atol=1e-6)
    assert checked >= 60
    assert old_rule_refused > 0  # the case the old tolerance refused is among these


def test_a_plan_from_another_state_is_refused_in_every_derivative() -> None:
    base = _flown()
    t_b = float(base.times[1]) + 0.3
    jet = _jet_at(base, t_b)
    for k, delta in enumerate((1e-4, 1e-3, 1e-2, 0.1, 5.0)):  # m, m/s, ..., m/s^4: small next to a plan's own
        for axis in range(3):
            off = jet.copy()
            off[k, axis] += delta
            stop = braking_trajectory(off, WIDE, None, t_b, durations=[0.8]).trajectory
            assert stop is not None
            refusal = swap_refusal(base, splice(base, stop), t_b - 0.3, 0.0, 50.0, t_b)
            assert refusal == SWAP_JETS if k else refusal != "", (k, axis, refusal)
