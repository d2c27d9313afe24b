"""What both command-line tools share (`cli` for plan/verify, `replan_cli` for replan):
the exit codes, the input error, reading a JSON input, printing an error line."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from planner_core.errors import FieldError

EXIT_OK = 0
EXIT_VERIFY_FAILED = 1
EXIT_INVALID = 2
EXIT_INFEASIBLE = 3


class InputError(FieldError):
    """An input file that cannot be read or is not JSON; `.field` names which input."""


def read_json(path: Path, what: str) -> Any:
    try:
        return json.loads(path.read_text())
    except OSError as e:
        raise InputError(what, f"cannot read {path}: {e.strerror}") from e
    except json.JSONDecodeError as e:
        raise InputError(what, f"{path}: invalid JSON ({e.msg} at line {e.lineno})") from e


def err(msg: str) -> None:
    print(f"error: {msg}", file=sys.stderr)
