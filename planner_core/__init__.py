"""Pure planning core: iterative Bernstein-polynomial QP planner (Strano, Furci, Marconi 2023).

The public door: everything here comes from `planner_core.api` (see its docstring, and its
`__all__` for the names); clients import nothing but `planner_core`. Names are resolved on
first use, so `import planner_core` costs only what is used (no scipy, numba or matplotlib
until something needs them).
"""

import sys
from types import ModuleType
from typing import TYPE_CHECKING, Any

from planner_core import api as _api
from planner_core.api import __all__ as __all__

if TYPE_CHECKING:
    from planner_core.api import *  # noqa: F403


def __getattr__(name: str) -> Any:
    value = getattr(_api, name)  # AttributeError for a name the door does not have
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


class _Door(ModuleType):
    def __setattr__(self, name: str, value: Any) -> None:
        # The import system binds each submodule on its package once it is loaded. Two share
        # their names with public functions (`replan`, `verify`): the function keeps the name,
        # as when everything was imported eagerly (the module stays in sys.modules).
        if isinstance(value, ModuleType) and name in __all__:
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Door
