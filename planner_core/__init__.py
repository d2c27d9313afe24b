"""Pure planning core: iterative Bernstein-polynomial QP planner (Strano, Furci, Marconi 2023).

The public door: everything here comes from `planner_core.api` (see its docstring, and its
`__all__` for the names); clients import nothing but `planner_core`.
"""

from planner_core.api import *  # noqa: F403
from planner_core.api import __all__ as __all__
