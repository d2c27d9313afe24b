"""The /commands/step channel: its JSON schema and the body of a record (every call of an
operator command sequence's rules, companion/command_rules.py). Apart from companion/channels.py,
which holds the other channels and is at its size limit; written as channels.py writes the
split-and-swap loop's /navigator/split.
"""

from __future__ import annotations

from typing import Any

from companion.channels import SEQ_RULES, T_MONO, TAGGED, _obj, _plain, _tagged

COMMAND_STEP = _obj("bezier.CommandStep", "One call of an operator command sequence's rules "
                    "(companion/command_rules.py command_step): for one run of a sequence (arm, takeoff, its climb, "
                    "land, abort, disarm, how a command ended, ...), what was observed (the autopilot's answer or "
                    "its timeout, the mode and armed state, the climb's swap), the state before and after, and what "
                    "the sequence did next; every value exact, as JSON holds it (no pickle)", {
    "seq": SEQ_RULES,
    "t": T_MONO,
    "transition": {"type": "integer", "description": "the /supervisor/transition seq the next transition gets (a "
                   "step whose action is a Transition: the one it makes)"},
    "call": {"type": "integer", "description": "the sequence's run (1, 2, ... per run of the service): its steps "
             "chain"},
    "step": {"type": "integer", "description": "1, 2, ... within the run"},
    "rules": {"type": "object", "description": "companion.command_rules.CommandRules: the run's sequence and givens"},
    "before": {"type": "object", "description": "companion.command_rules.CommandState"},
    "observation": TAGGED, "after": {"type": "object"}, "action": TAGGED,
}, ("seq", "t", "transition", "call", "step", "rules", "before", "observation", "after", "action"))


def command_fields(call: int, step: int, rules: Any, before: Any, observation: Any, after: Any,
                   action: Any) -> dict[str, Any]:
    """The readable part of a /commands/step record: all of it (JSON only)."""
    return {"call": call, "step": step, "rules": _plain(rules), "before": _plain(before),
            "observation": _tagged(observation), "after": _plain(after), "action": _tagged(action)}
