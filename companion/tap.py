"""The service's one listening point for the flight recorder and the live view.

Each place where something enters or leaves the service calls one method of a `Tap` with what
it has at hand (bytes already encoded, the pymavlink message, the planner's arguments and
result) and the monotonic time. `Tap` itself does nothing, so a service without a recorder
pays one method call; `companion.recorder.Recorder` queues each call (O(1), never blocking)
for its writer thread, which does every conversion. Some calls come from the setpoint thread
(a setpoint sent) and from Zenoh's and the executors' threads: a Tap must be thread-safe and
must never wait.
"""

from __future__ import annotations

from typing import Any


class Tap:
    """A no-op: what the service calls when nothing records."""

    def inbound(self, key: str, payload: Any, t: float) -> None:
        """A Zenoh message taken in: its key's last part, bytes (or `Oversized`), arrival time."""

    def outbound(self, key: str, payload: bytes, t: float) -> None:
        """A Zenoh publication: its key's last part and the bytes published."""

    def decoded(self, key: str, payload: Any, context: dict[str, Any], result: Any, t: float) -> None:
        """An inbound message read (companion.wire.messages.read): its key's last part, the bytes
        (or `Oversized`), what else `read` was given (`home`, `home_pending`, `fleet`, `autopilot`), and what
        it made of them (a typed message or the MessageError that refuses it); its arrival time."""

    def mavlink_sent(self, msg: Any, t: float | None = None) -> None:
        """A MAVLink message just written to the link (setpoints included); pymavlink's send
        callback, so no time: the tap takes it."""

    def mavlink_received(self, msg: Any, t: float) -> None:
        """A MAVLink message from the vehicle, as the link accepted it."""

    def plan(self, fn: Any, args: tuple[Any, ...], result: Any, submitted: float, done: float,
             where: str) -> None:
        """A planner call: the function, its arguments, its result (or the exception raised),
        when it was submitted and when its result was back on the loop, and where it ran."""

    def transition(self, before: Any, event: Any, after: Any, actions: tuple[Any, ...]) -> None:
        """A `Supervisor.handle` call (companion/supervisor.py): the flight state before, the
        event, the state after and the actions, as immutable values; on the loop, so no time:
        the tap takes it."""

    def autopilot_step(self, before: Any, flight: Any, reading: Any, now: float, after: Any,
                       outputs: tuple[Any, ...]) -> None:
        """A call of the autopilot watch's rules (companion.autopilot_rules.watch_step): the
        watch's state before, the flight state read, the reading, its time, the state after and
        the outputs, as immutable values; on the loop."""

    def swap(self, what: str, now: float, lead: float, rate_hz: float, t_split: float, old: Any, new: Any,
             refusal: str) -> None:
        """A decision of the swap's rule (companion.control.swap_refusal): what asked, the
        trajectory time now, the lead and the rate, the split, the flown and the new trajectory,
        and the refusal ("" swapped in); on the loop, so no time: the tap takes it."""
    def tracking_step(self, before: Any, reading: Any, after: Any, outputs: tuple[Any, ...], t: float) -> None:
        """A call of the tracking error's rules (companion.tracking_rules.tracking_step) that
        changed their state or said something: the state before, the reading, the state after
        and the outputs, as immutable values, and the sample's time; on the loop."""

    def split_step(self, call: int, step: int, what: str, rules: Any, before: Any, observation: Any, after: Any,
                   action: Any) -> None:
        """A call of the split-and-swap loop's rules (companion.split_rules.split_step): the
        `at_split` call's number and the step's within it, what asked, the call's rules, the
        state before, the observation, the state after and the action; on the loop, so no time:
        the tap takes it."""

    def commit_step(self, before: Any, event: Any, after: Any, actions: tuple[Any, ...]) -> None:
        """A call of the fleet's commit protocol (companion.commit.step): the state before, the
        event, the state after and the actions; on the loop, so no time: the tap takes it."""

    def clock_sample(self, vehicle: str, sent: float, arrived: float, off: str | None) -> None:
        """A sample of the fleet's clock check (companion.clocks) and the verdict on our clock
        after it; on the loop, so no time: the tap takes it."""

    def budget_step(self, before: Any, ask: Any, after: Any, answer: Any) -> None:
        """A question to the plan budget (companion.plan_budget.budget_step): the budget before,
        the question, the budget after and the answer; on the loop, so no time: the tap takes it."""

    def race_step(self, race: int, step: int, rules: Any, before: Any, observation: Any, after: Any,
                  action: Any) -> None:
        """A call of a pop-up's rules (companion.race_rules.race_step): the pop-up's number and
        the step's within it, its rules, the state before, the observation, the state after and
        the action; on the loop, so no time: the tap takes it."""

    def command_step(self, call: int, step: int, rules: Any, before: Any, observation: Any, after: Any,
                     action: Any) -> None:
        """A call of an operator command sequence's rules (companion.command_rules.command_step):
        the run's number and the step's within it, the run's rules, the state before, the
        observation, the state after and the action; on the loop, so no time: the tap takes it."""

    def stall_step(self, rules: Any, before: Any, observation: Any, after: Any, action: Any) -> None:
        """A call of the stall rules (companion.stall_rules.stall_step) that changed their state,
        found a stall or settled (at the start, after a stall): the rules, the state before, the observation, the state after and the
        action; on the loop, so no time: the tap takes it."""

    def hold_step(self, call: int, step: int, rules: Any, before: Any, observation: Any, after: Any,
                  action: Any) -> None:
        """A call of the hand-over's hold rules (companion.hold_rules.hold_step): the hold's number
        and the step's within it, the rules, the state before, the observation, the state after
        and the action; on the loop, so no time: the tap takes it."""

    def choice_step(self, call: int, step: int, rules: Any, before: Any, observation: Any, after: Any,
                    action: Any) -> None:
        """A call of the navigator's plan choice (companion.choice_rules.choice_step): the run's
        number and the step's within it, the rules, the state before, the observation, the state
        after and the action; on the loop, so no time: the tap takes it."""

    def flown(self, trajectory: Any, t_base: float | None, t: float) -> None:
        """What the setpoint thread flies from now on (a new plan, a swap, a hold)."""

    def status_fields(self) -> dict[str, Any]:
        """Fields for the service's status (nothing when nothing records)."""
        return {}

    def open(self) -> None:
        """Start recording (files, live server, writer thread)."""

    def close(self) -> None:
        """Write out what is queued and close files and servers."""


NO_TAP = Tap()
