"""Issue 22.3: the inbound message types are defined once, in the JSON Schemas the decoder
validates with (companion/schemas); the protocol reference in docs/protocol.md is held to them:
every field and every enumerated value a schema admits is documented in its message's section
(or in "Frames and origins", which the positional messages share), and every field the
section's examples use is one the schema admits."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest

from companion.wire.decode import schema
from companion.wire.messages import KINDS

DOC = (Path(__file__).resolve().parents[2] / "docs" / "protocol.md").read_text()


def section(title: str) -> str:
    m = re.search(rf"^##+ {re.escape(title)}.*?$(.*?)(?=^##+ )", DOC, re.S | re.M)
    assert m is not None, f"docs/protocol.md has no section {title!r}"
    return m.group(1)


def walk(node: Any, fields: set[str], values: set[str]) -> None:
    """Every property name and every string enum value under a schema node."""
    if isinstance(node, dict):
        for k, v in node.get("properties", {}).items():
            fields.add(k)
            walk(v, fields, values)
        values.update(x for x in node.get("enum", []) if isinstance(x, str))
        if isinstance(node.get("const"), str):
            values.add(node["const"])
        for key in ("oneOf", "anyOf", "allOf", "items", "$defs", "additionalProperties", "then", "else", "if"):
            if key in node:
                walk(node[key] if key != "$defs" else list(node[key].values()), fields, values)
    elif isinstance(node, list):
        for x in node:
            walk(x, fields, values)


def admitted(kind: str) -> tuple[set[str], set[str]]:
    fields: set[str] = set()
    values: set[str] = set()
    walk(schema(kind), fields, values)
    return fields, values


@pytest.mark.parametrize("kind", KINDS)
def test_every_field_and_value_of_the_schema_is_documented(kind: str) -> None:
    text = section(f"`{kind}` (in)") + section("Frames and origins")
    fields, values = admitted(kind)
    missing = sorted(f for f in fields if not re.search(rf"[`\"]{re.escape(f)}[`\"]", text))
    assert not missing, f"docs/protocol.md, `{kind}`: fields the schema admits but the section never names: {missing}"
    missing = sorted(v for v in values if not re.search(rf"[`\"]{re.escape(v)}[`\"]", text))
    assert not missing, f"docs/protocol.md, `{kind}`: values the schema admits but the section never names: {missing}"


@pytest.mark.parametrize("kind", KINDS)
def test_every_field_the_examples_use_is_in_the_schema(kind: str) -> None:
    fields, _ = admitted(kind)
    examples = "".join(re.findall(r"```json\n(.*?)```", section(f"`{kind}` (in)"), re.S))
    examples += "".join(re.findall(r"`(\{.*?\})`", section(f"`{kind}` (in)")))
    used = set(re.findall(r"\"(\w+)\"\s*:", examples))
    assert used, f"no examples found for {kind}"
    # the events shown beside the examples are outbound (their fields are not the message's)
    outbound = {"type", "key", "mission", "plan_ms", "field", "reason", "command", "method", "split_time",
                "replan_ms", "resolved_jets", "latency_ms"}
    unknown = sorted(used - fields - outbound)
    assert not unknown, f"docs/protocol.md, `{kind}`: example fields the schema does not admit: {unknown}"
