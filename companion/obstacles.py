"""The obstacles the companion knows, and how they and the mission's waypoints are named back.

One owner (`ObstacleStore`) of the obstacles sent on the `obstacles` key; `Known` is the
snapshot handed to a planner: every obstacle that counts (the store's and the mission's own),
with the ids the operator gave, so that a refusal names `wall`, not "obstacle 1".
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from planner_core import FloatArray, Polytope


@dataclass(frozen=True)
class Known:
    """Obstacles for one planning call: polytopes (NED) and their ids, index for index."""

    ids: tuple[str, ...] = ()
    polytopes: tuple[Polytope, ...] = ()

    def name(self, index: int | None) -> str:
        if index is None or not 0 <= index < len(self.ids):
            return "an obstacle"
        return f"obstacle '{self.ids[index]}'"

    def without(self, drop: Iterable[Polytope]) -> Known:
        gone = {id(p) for p in drop}
        pairs = [(i, p) for i, p in zip(self.ids, self.polytopes, strict=True) if id(p) not in gone]
        return Known(tuple(i for i, _ in pairs), tuple(p for _, p in pairs))

    def only(self, keep: Sequence[Polytope]) -> Known:
        """`keep` (by identity, in its order) with the ids they have here ("a new obstacle" if none)."""
        ids = {id(p): i for i, p in zip(self.ids, self.polytopes, strict=True)}
        return Known(tuple(ids.get(id(p), "a new obstacle") for p in keep), tuple(keep))

    def __add__(self, other: Known) -> Known:
        return Known(self.ids + other.ids, self.polytopes + other.polytopes)

    @staticmethod
    def of(pairs: Sequence[tuple[str, Polytope]]) -> Known:
        return Known(tuple(i for i, _ in pairs), tuple(p for _, p in pairs))


class ObstacleStore:
    """Obstacles by id, as sent on the `obstacles` key (NED), at most `max_held` of them
    ([limits] max_obstacles_held): every plan is built against all of them."""

    def __init__(self, max_held: int | None = None) -> None:
        self._by_id: dict[str, Polytope] = {}
        self.max_held = max_held

    def refusal(self, add: Sequence[tuple[str, Polytope]], remove: Sequence[str], clear: bool) -> str | None:
        """Why this update may not be applied (None: it may): it would hold too many."""
        if self.max_held is None:
            return None
        kept = set() if clear else set(self._by_id) - set(remove)
        n = len(kept | {k for k, _ in add})
        if n > self.max_held:
            return (f"{n} obstacles would be held, more than the limit of {self.max_held} "
                    f"([limits] max_obstacles_held; {len(self._by_id)} held now: remove or clear some first)")
        return None

    def update(self, add: Sequence[tuple[str, Polytope]], remove: Sequence[str], clear: bool
               ) -> tuple[list[str], list[str], list[str]]:
        """Apply an update; returns (added, removed, unknown ids asked to be removed)."""
        removed = list(self._by_id) if clear else [k for k in remove if k in self._by_id]
        unknown = [] if clear else [k for k in remove if k not in self._by_id]
        for k in removed:
            del self._by_id[k]
        for k, p in add:
            self._by_id[k] = p
        return sorted(k for k, _ in add), sorted(removed), unknown

    def ids(self) -> list[str]:
        return sorted(self._by_id)

    def known(self) -> Known:
        """The store's obstacles (the planners add the mission's own)."""
        return Known.of(list(self._by_id.items()))

    def __len__(self) -> int:
        return len(self._by_id)


def waypoint_name(labels: FloatArray, i: int) -> str:
    """Route waypoint i as the operator knows it."""
    if 0 <= i < len(labels) and labels[i] >= 0:
        return f"mission waypoint {int(labels[i])}"
    return "the current position" if i == 0 else "a detour point"


def blocked_text(labels: FloatArray, segment: int | None, waypoint: int | None, obstacle: str) -> tuple[str, int | None]:
    """What is blocked, in mission terms, and the mission index of a blocked waypoint."""
    if segment is not None and 0 <= segment < len(labels) - 1:
        return (f"the path from {waypoint_name(labels, segment)} to {waypoint_name(labels, segment + 1)} "
                f"is blocked by {obstacle}"), None
    if waypoint is not None and 0 <= waypoint < len(labels):
        mission = int(labels[waypoint]) if labels[waypoint] >= 0 else None
        return f"{waypoint_name(labels, waypoint)} is blocked by {obstacle}", mission
    return f"no free corridor ({obstacle} is in the way)", None


def as_known(obstacles: Known | Sequence[Polytope]) -> Known:
    """Obstacles with ids; plain polytopes (tests, tools) are named by their index."""
    if isinstance(obstacles, Known):
        return obstacles
    polys = tuple(obstacles)
    return Known(tuple(str(i) for i in range(len(polys))), polys)
