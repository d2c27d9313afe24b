"""`python -m companion replay FILE.mcap`: run every recorded supervisor transition and every
recorded plan again and compare bit for bit.

Transitions: each `/supervisor/transition` record holds one `Supervisor.handle` call (the
state before, the event, the state after, the actions). Replay runs `transition(before, event)`
again and compares the state and the actions with the recorded ones exactly, and checks the
chain: each record starts from the state the one before it ended in, and the numbers have no
gap (a state replaced outside `handle`, a record removed or one the recorder dropped shows).

Autopilot steps: each `/autopilot/step` record holds one call of the autopilot watch's rules
(companion/autopilot_rules.py: a MAVLink reading or a link check to supervisor events), run
again and matched to the transitions its events caused (companion/replay_autopilot.py).

Tracking steps: each `/tracking/step` record holds one call of the tracking error's rules
(companion/tracking_rules.py: when it brakes and when it warns), run again and each brake it
asked for found among the transitions (companion/replay_tracking.py).

Inbound messages: each `/inbound/decoded` record is read again with the recorded configuration.

Plans: each `/planner/plan` record holds the planner call the service made (the function and
its arguments: the mission, the jet to start from, the known obstacles, the configuration, the
route and trajectory being replanned) and its result. Replay runs the same function on the
same arguments, in this process, with the same planner path (the numpy path unless the record
says the compiled one ran), and compares the result with the recorded one: every array bit for
bit, every number by its exact binary value, every string, leaving out only the `stats`
dictionaries (timings).

Swaps and split steps: each `/control/swap` record holds one decision of the swap's rule,
decided again (companion/replay_swaps.py); each `/navigator/split` record one call of the
split-and-swap loop's rules (where a plan made in flight splits, planning again, moving it later,
giving up), run again (companion/replay_split.py); each `/navigator/budget` record one question
to the plan budget (how far ahead a plan splits, how big a search fits, each plan's time
measured), answered again (companion/replay_budget.py); each `/brakes/race` record one call of
a pop-up obstacle's rules (announce, no replan, brake now or race; the braking deadline brought
forward; each turn of the race; its end), run again, each brake found among the transitions
(companion/replay_race.py); in a fleet, each `/fleet/commit` record one call of the commit
protocol's rule, run again (companion/replay_commit.py).

Command steps: each `/commands/step` record holds one call of an operator command sequence's
rules (companion/command_rules.py: arm, takeoff and its climb, land, abort, disarm, how a
command ended), run again and each transition it made found (companion/replay_commands.py).

Plan choices: each `/navigator/choice` record holds one call of the navigator's plan choice
(companion/choice_rules.py: which planner call a mission's start, a replan or a stop asks for,
and what it makes of the answer: the search after an infeasible quick start, the remainder after
a local replan, the prepared stop or a hold), run again and each planner call chosen found among
the plan records (companion/replay_choice.py).

(companion/choice_rules.py also decides the improvement of a quick start and the `start`
command: take off, take control, fly what is loaded or resume.)

What it does not cover: the autopilot watch's telemetry advice (a text for the operator) is not
re-run; it is in the file (events, status) to be read.

A recording comes from a companion you trust: the calls are pickled. Plan records are read with
an allow-list (planner_core and companion data classes and planner functions, numpy arrays,
plain containers), transition and autopilot step records with narrower ones (the flight state,
its enum, the supervisor's events and actions; the watch's state, readings and outputs); tracking
step records are JSON, typed again into the rules' own classes by name. So a file cannot name any
other function to call; still, do not replay files from unknown sources.
"""

from __future__ import annotations

import base64
import builtins
import dataclasses
import enum
import functools
import io
import pickle
import time
from collections.abc import Callable, Iterator
from typing import Any

from companion.record_format import (
    decoded_fingerprint,
    decoded_summary,
    fingerprint,
    first_difference,
    summary_of,
)

# -- reading calls back -------------------------------------------------------------------------

_NUMPY = {
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"), ("numpy", "dtype"), ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.numeric", "_frombuffer"),
}
_PLAIN = {
    ("copyreg", "_reconstructor"), ("copyreg", "__newobj__"), ("builtins", "object"), ("builtins", "set"),
    ("builtins", "frozenset"), ("builtins", "slice"), ("builtins", "complex"),
    ("functools", "partial"), ("collections", "OrderedDict"),
}


class _SafeUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _PLAIN:
            return super().find_class(module, name)
        if (module, name) in _NUMPY or module.startswith("numpy.dtypes"):
            return super().find_class(module, name)
        if module.startswith(("planner_core", "companion")) and not module.startswith(
                ("planner_core.formats", "companion.__main__", "companion.cli_", "companion.service")):
            obj = super().find_class(module, name)
            if isinstance(obj, type) and (dataclasses.is_dataclass(obj) or issubclass(obj, enum.Enum | BaseException)):
                return obj
            if callable(obj) and not isinstance(obj, type) and (
                    module.startswith("planner_core") or module in ("companion.mission", "companion.route")):
                return obj  # a planner function: what a recorded call names
        if module == "builtins":
            obj = getattr(builtins, name, None)
            if isinstance(obj, type) and issubclass(obj, BaseException):
                return obj
        raise pickle.UnpicklingError(f"replay does not load {module}.{name} from a recording")


def loads(text: str) -> Any:
    return _SafeUnpickler(io.BytesIO(base64.b64decode(text))).load()


@functools.cache
def _supervisor_types() -> frozenset[tuple[str, str]]:
    """The classes a transition record holds: the flight state and its enum, the supervisor's
    events and actions (nothing callable but these constructors)."""
    import typing

    from companion import supervisor
    from companion.flight import FlightState, State

    kinds = (FlightState, State, *typing.get_args(supervisor.Event), *typing.get_args(supervisor.Action))
    return frozenset((k.__module__, k.__qualname__) for k in kinds)


class _Narrow(pickle.Unpickler):
    """Loads only the classes named in `allowed` (module, qualified name)."""

    def __init__(self, data: bytes, allowed: frozenset[tuple[str, str]], what: str) -> None:
        super().__init__(io.BytesIO(data))
        self.allowed, self.what = allowed, what

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self.allowed:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"replay does not load {module}.{name} from {self.what}")


NUMPY_CLASSES = frozenset(_NUMPY)  # what a pickled numpy array names


def loads_narrow(text: str, allowed: frozenset[tuple[str, str]], what: str) -> Any:
    """A record's pickle (base64) with only the `allowed` classes (a record of `what`)."""
    return _Narrow(base64.b64decode(text), allowed, what).load()


def loads_transition(text: str) -> Any:
    return loads_narrow(text, _supervisor_types(), "a transition record")


# -- the replay ---------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Replayed:
    seq: int
    function: str
    identical: bool
    recorded_ms: float
    replayed_ms: float
    difference: str = ""


def recorded_metadata(path: str) -> dict[str, dict[str, str]]:
    """The file's metadata records by name (none in a file cut short: no summary, no index)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as fh:
            return {m.name: dict(m.metadata) for m in make_reader(fh).iter_metadata()}
    except (McapError, ValueError):  # no summary: no metadata index
        return {}


def recorded_environment(path: str) -> dict[str, str]:
    import json

    meta = recorded_metadata(path).get("companion", {})
    env: dict[str, str] = json.loads(meta["environment"]) if "environment" in meta else {}
    return env


def records(path: str, topics: tuple[str, ...]) -> Iterator[tuple[str, float, dict[str, Any]]]:
    """(topic, seconds from the recording's start, record) of the JSON records on `topics`;
    the start is the file's first message of any channel."""
    import json

    from companion.recording import read_messages

    start = None
    for _schema, channel, message in read_messages(path):
        if start is None:
            start = message.log_time
        if channel.topic in topics:
            yield channel.topic, (message.log_time - start) / 1e9, json.loads(message.data)


def _within(rel: float, since: float | None, until: float | None) -> bool:
    return (since is None or rel >= since) and (until is None or rel <= until)


def plan_records(path: str, since: float | None = None, until: float | None = None) -> Iterator[dict[str, Any]]:
    """The /planner/plan records of a file; `since`/`until`: seconds from the recording's start."""
    for _topic, rel, rec in records(path, ("/planner/plan",)):
        if until is not None and rel > until:
            break
        if _within(rel, since, until):
            yield rec


def numbered_records(path: str, topic: str, kind: str, since: float | None = None,
                     until: float | None = None) -> tuple[list[dict[str, Any]], int]:
    """The records on `topic` (each numbered by `seq`) of a file, in `seq` order (`since`/`until`
    as for plans), and how many records of `kind` the recorder said it dropped: its `recorder`
    metadata, or the last /recorder/stats of a file cut short; counted over the whole run."""
    import json

    found: list[dict[str, Any]] = []
    dropped = 0
    for name, rel, rec in records(path, (topic, "/recorder/stats")):
        if name == "/recorder/stats":
            dropped = max(dropped, int(rec.get("dropped", {}).get(kind, 0)))
        elif _within(rel, since, until):
            found.append(rec)
    meta = recorded_metadata(path).get("recorder", {})
    if "dropped" in meta:
        dropped = max(dropped, int(json.loads(meta["dropped"]).get(kind, 0)))
    return sorted(found, key=lambda r: int(r["seq"])), dropped


def transition_records(path: str, since: float | None = None,
                       until: float | None = None) -> tuple[list[dict[str, Any]], int]:
    """The /supervisor/transition records of a file and the transition records dropped (numbered_records)."""
    return numbered_records(path, "/supervisor/transition", "transition", since, until)


def replay_one(rec: dict[str, Any]) -> Replayed:
    from planner_core import use_compiled_kernel

    name = rec["function"]
    if rec.get("call") is None:
        return Replayed(rec["seq"], name, False, rec.get("latency_ms", 0.0), 0.0, "the call was not recorded (not picklable)")
    fn, args = loads(rec["call"])
    # process-wide switch: borrowed for this call only, or a library user's later plans (and
    # the next test in the same process) would run as the recording did
    before = use_compiled_kernel(bool(rec.get("compiled")), "replay: as recorded")
    t0 = time.perf_counter()
    try:
        result: Any = fn(*args)
    except Exception as exc:
        result = exc
    finally:
        use_compiled_kernel(before is None, before or "")
    took = (time.perf_counter() - t0) * 1000
    if fingerprint(result) == rec["fingerprint"]:
        return Replayed(rec["seq"], name, True, rec.get("latency_ms", 0.0), took)
    if rec.get("result") is not None:
        recorded = loads(rec["result"])
        if fingerprint(recorded) == fingerprint(result):
            # the recording predates a field added to a result type since: read back, that field
            # takes its default, and every value the recording holds is reproduced
            return Replayed(rec["seq"], name, True, rec.get("latency_ms", 0.0), took)
        why = first_difference(recorded, result)
    else:
        why = f"recorded {rec.get('message')!r}, replayed {summary_of(result).get('message')!r}"
    return Replayed(rec["seq"], name, False, rec.get("latency_ms", 0.0), took, why)


# -- transitions --------------------------------------------------------------------------------


@dataclasses.dataclass
class Chain:
    """What replaying a chain of numbered records found: `reproduced` of `total` (the records,
    and the numbers missing between them), and every difference in `seq` order."""

    total: int = 0
    reproduced: int = 0
    differences: list[str] = dataclasses.field(default_factory=list)




class RulesReader:
    """Reads a recorded rules value (`{"type": class name, "fields": ...}`) back into one of the
    classes `kinds()` names (a rules module's observations and actions), by name; any other is
    refused (ValueError), so a JSON record can make nothing but the rules' own values. `tuples`:
    fields JSON holds as lists that the classes hold as tuples."""

    def __init__(self, kinds: Callable[[], tuple[type, ...]], what: str, tuples: tuple[str, ...] = ()) -> None:
        self._kinds = kinds
        self._by_name: dict[str, type] | None = None  # on first use: the rules module loads then
        self.what = what
        self.tuples = tuples

    def __call__(self, tagged: dict[str, Any]) -> Any:
        if self._by_name is None:
            self._by_name = {k.__name__: k for k in self._kinds()}
        kind = self._by_name.get(tagged["type"])
        if kind is None:
            raise ValueError(f"{tagged['type']!r} is not {self.what}")
        fields = tagged["fields"]
        if self.tuples:
            fields = {k: tuple(v) if k in self.tuples and isinstance(v, list) else v for k, v in fields.items()}
        return kind(**fields)


def rule_values(rec: dict[str, Any], rules: Callable[..., Any], state: Callable[[dict[str, Any]], Any],
                typed: RulesReader) -> tuple[Any, Any, Any, Any, Any]:
    """(rules, before, observation, after, action) of a record of one call of a decision rule
    (channels.rule_fields), typed again from its JSON into the rules' own classes: `rules` and
    `state` build the rules and a state from their fields, `typed` the observation and action
    (a record naming another class is refused: TypeError, ValueError)."""
    return (rules(**rec["rules"]), state(rec["before"]), typed(rec["observation"]), state(rec["after"]),
            typed(rec["action"]))


def observations_and_actions(module: str) -> Callable[[], tuple[type, ...]]:
    """The classes of a rules module's `Observation` and `Action` unions (imported when asked)."""
    def kinds() -> tuple[type, ...]:
        import importlib
        import typing

        rules = importlib.import_module(module)
        return (*typing.get_args(rules.Observation), *typing.get_args(rules.Action))

    return kinds


def said_of(name: str, chain: Chain, recorded: bool, detail: str, alike: str = "reproduced") -> str:
    """The replay's line for a file's `name` records: none recorded, the first difference, or
    every one `alike` (`detail`: what they did)."""
    if not recorded:
        return f"{name}: none recorded"
    if chain.differences:
        return f"{name}: {chain.reproduced} of {chain.total} {alike}; first difference: {chain.differences[0]}"
    return f"{name}: {chain.total} of {chain.total} {alike} ({detail})"

Transitions = Chain
Check = Callable[[dict[str, Any], "tuple[int, Any] | None"], "tuple[Any, list[str]]"]


def replay_chain(out: Chain, recs: list[dict[str, Any]], check: Check, dropped: int, what: str) -> Chain:
    """Every record (in `seq` order) through `check(record, previous)` -> (its recorded state
    after, or None if unreadable; what differs), `previous` the seq and state after of the
    record just before it (None: nothing to chain to). A gap in the numbers, and records of
    `what` the recorder counted as dropped, are differences: the chain cannot be checked across them."""
    out.total += len(recs)
    previous: tuple[int, Any] | None = None
    last: int | None = None
    for rec in recs:
        seq = int(rec["seq"])
        if last is not None and seq != last + 1:
            if seq == last:
                out.differences.append(f"seq {seq} recorded twice")
            else:
                missing = seq - last - 1
                out.total += missing
                where = f"seq {last + 1}" if missing == 1 else f"seq {last + 1} to {seq - 1}"
                out.differences.append(f"{where} missing ({missing} record{'s' * (missing > 1)}: dropped by the "
                                       "recorder, or removed): the chain is not checkable there")
            previous = None
        after, why = check(rec, previous)
        out.differences.extend(why)
        out.reproduced += not why
        previous = None if after is None else (seq, after)
        last = seq
    if dropped:
        out.differences.append(f"the recorder dropped {dropped} {what} record{'s' * (dropped > 1)} in this run "
                               "(its queue was full): the chain is not checkable across them")
    return out


def _label(seq: int, event: Any) -> str:
    return f"seq {seq} {event!r}"


def check_transition(rec: dict[str, Any], previous: tuple[int, Any] | None) -> tuple[Any, list[str]]:
    """Run one record through `transition` again: (its recorded state after, for the next
    record's chain check, or None if unreadable; what differs). `previous`: the seq and the
    recorded state after of the record just before it (None: nothing to chain to)."""
    import json

    from companion.channels import dumps, transition_fields
    from companion.supervisor import transition

    seq = int(rec["seq"])
    if rec.get("pickle") is None:
        return None, [f"seq {seq} {rec['event'].get('type')}: the values were not recorded (not picklable)"]
    before, event, after, actions = loads_transition(rec["pickle"])
    label, why = _label(seq, event), []
    # what a viewer shows of the record is what is replayed here
    readable = json.loads(dumps(transition_fields(before, event, after, actions)))
    for name, value in readable.items():
        if rec.get(name) != value:
            why.append(f"{label}: the record's {name} (JSON) is not its pickled value")
    why += chained(label, before, previous, "the state was replaced outside Supervisor.handle")
    try:
        new, acts = transition(before, event)
    except Exception as exc:  # the recorded call returned: raising now is a difference
        why.append(f"{label}: replayed raised {type(exc).__name__}: {exc}")
        return after, why
    return after, why + compared(label, ("after", after, new), ("actions", tuple(actions), tuple(acts)))


def chained(label: str, before: Any, previous: tuple[int, Any] | None, replaced: str) -> list[str]:
    """A record's state `before` against the state after of the record before it (`previous`:
    its seq and that state; None: nothing to chain to); `replaced`: what it means if they differ."""
    if previous is None or fingerprint(before) == fingerprint(previous[1]):
        return []
    where = first_difference(previous[1], before, "before", (f"seq {previous[0]} ended in", "this one starts from"))
    return [f"{label}: does not start where seq {previous[0]} ended ({where}): {replaced}, or a record was altered"]


@dataclasses.dataclass(frozen=True)
class RunStep:
    """A run's last step as replay saw it: its number, rules, state after, seq and action."""

    step: int
    rules: Any
    after: Any
    seq: int
    action: Any


class RunChains:
    """The records of a rule stepped in runs (a command sequence, a race, a split, a hold, a
    plan choice: companion.rule_run.RuleRun), chained per run: a run's step 1 starts from the
    state a run starts with (`fresh(rules)`, said as `start`); a later one from where the run's
    step before ended (`replaced`: what it means if not), under the same rules."""

    def __init__(self, fresh: Callable[[Any], Any], replaced: str, start: str = "before") -> None:
        self.fresh = fresh
        self.replaced = replaced
        self.start = start
        self.last: dict[int, RunStep] = {}

    def chain(self, label: str, run: int, step: int, seq: int, rules: Any, before: Any, after: Any,
              action: Any) -> tuple[list[str], RunStep | None]:
        """Where this step does not start as its run left off, and the run's step before it
        (None: the first, or one the chain cannot reach across a gap)."""
        why: list[str] = []
        last = self.last.get(run)
        prior = None
        if step == 1:
            why += compared(label, (self.start, self.fresh(rules), before))
        elif last is not None and last.step == step - 1:
            why += chained(label, before, (last.seq, last.after), self.replaced)
            why += compared(label, ("rules", last.rules, rules))
            prior = last
        self.last[run] = RunStep(step, rules, after, seq, action)
        return why, prior


def compared(label: str, *values: tuple[str, Any, Any]) -> list[str]:
    """(name, recorded, replayed) compared exactly: where each pair differs first."""
    return [f"{label}: {first_difference(was, now, name)}" for name, was, now in values
            if fingerprint(was) != fingerprint(now)]


def replay_transitions(recs: list[dict[str, Any]], dropped: int = 0) -> Transitions:
    """Every record (in `seq` order) run again and chained to the one before it (replay_chain)."""
    return replay_chain(Chain(), recs, check_transition, dropped, "transition")


def transitions_by_seq(recs: list[dict[str, Any]]) -> dict[int, tuple[Any, Any, Any]]:
    """(before, event, after) of each readable transition record, by seq."""
    out: dict[int, tuple[Any, Any, Any]] = {}
    for rec in recs:
        if rec.get("pickle") is not None:
            before, event, after, _actions = loads_transition(rec["pickle"])
            out[int(rec["seq"])] = (before, event, after)
    return out


def recorded_config(path: str) -> Any:
    """The configuration the recording service ran with (its `companion` metadata), or None."""
    import tomllib

    from companion.config import config_from_dict

    text = recorded_metadata(path).get("companion", {}).get("config")
    return None if text is None else config_from_dict(tomllib.loads(text))


def required_config(path: str, to: str) -> Any:
    """The recording's configuration (recorded_config), which it needs `to` do something: its
    absence is the file's fault (ValueError)."""
    cfg = recorded_config(path)
    if cfg is None:
        raise ValueError(f"the recording holds no configuration to {to}")
    return cfg


def decoded_records(path: str, since: float | None = None, until: float | None = None) -> list[dict[str, Any]]:
    """The /inbound/decoded records of a file, in `seq` order (`since`/`until` as for plans)."""
    found = [rec for _t, rel, rec in records(path, ("/inbound/decoded",)) if _within(rel, since, until)]
    return sorted(found, key=lambda r: int(r["seq"]))


def replay_decoded(rec: dict[str, Any], cfg: Any) -> str:
    """Read the recorded message again as the service did: "" when it becomes the same typed
    message (or the same refusal, word for word), else what differs."""
    from companion.wire.errors import Oversized
    from companion.wire.messages import read

    if rec.get("call") is None:
        return f"message {rec['seq']} on {rec['key']}: its inputs could not be recorded"
    call = loads(rec["call"])
    key, raw, home, home_pending, fleet = call[:5]
    autopilot = call[5] if len(call) > 5 else None  # recorded before the per-autopilot allowance: not said
    payload = Oversized(raw) if isinstance(raw, int) else raw
    result = read(key, payload, cfg, home, home_pending=home_pending, fleet=fleet, autopilot=autopilot)
    if decoded_fingerprint(result) == rec["fingerprint"]:
        return ""
    now = decoded_summary(result)
    was = f"{rec['type']}" + ("" if rec["ok"] else f" ({rec.get('field') or 'payload'}: {rec.get('reason')})")
    got = f"{now['type']}" + ("" if now["ok"] else f" ({now['field'] or 'payload'}: {now['reason']})")
    return f"message {rec['seq']} on {key}: recorded {was}, read again {got}" if was != got else \
        f"message {rec['seq']} on {key}: the {got} read again differs in its values"
