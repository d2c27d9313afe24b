"""One base for every error that names an offending input field.

`FieldError(field, reason)` is a `ValueError` whose message is "field: reason";
`.field` says where (a dotted/indexed path such as "move.index" or
"waypoints[3]") and `.reason` says what is wrong. Subclasses: `ChangeError`
(planner_core.changes), `CorridorError` (planner_core.geometry),
`ScenarioError` (planner_core.formats.io) and `InputError`
(planner_core.formats.cli).
"""

from __future__ import annotations

from typing import Any


class FieldError(ValueError):
    """Invalid input, naming the field at fault: str(e) == f"{e.field}: {e.reason}".

    A subclass that already has its own wording may pass `message` to keep it;
    `.field` and `.reason` are set all the same.
    """

    def __init__(self, field: str, reason: str, *, message: str | None = None) -> None:
        super().__init__(f"{field}: {reason}" if message is None else message)
        self.field = field
        self.reason = reason

    def __reduce__(self) -> tuple[Any, ...]:
        # picklable whatever a subclass's __init__ takes (errors cross to and from workers)
        return (_rebuild, (type(self), self.args, dict(self.__dict__)))


def _rebuild(cls: type[FieldError], args: tuple[Any, ...], state: dict[str, Any]) -> FieldError:
    err = cls.__new__(cls)
    err.args = args
    err.__dict__.update(state)
    return err


__all__ = ["FieldError"]
