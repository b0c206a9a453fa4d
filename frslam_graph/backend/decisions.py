"""The decision log: one typed event per decision of the backend, written once by its owner.

Registrations, relocalisations, floor-plan priors added / rejected / removed, loop closures,
odometry faults, the final batch: each is one :class:`DecisionEvent` (``stamp`` in seconds of the
recording, ``keyframe`` its graph index when it concerns one, ``data`` the numbers behind it).
``frslam run`` writes the log as ``log.jsonl`` (one event per line). Nothing is printed.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, get_args, overload

#: why a floor-plan prior left the graph (``prior_removed`` events, ``metrics.json`` ``priors``)
PriorRemoval = Literal["wrong", "re-anchored"]
PRIOR_REMOVAL_CAUSES: tuple[str, ...] = get_args(PriorRemoval)


@dataclass(frozen=True, slots=True)
class DecisionEvent:
    """One entry of the decision log: what happened, when, and the numbers behind it.

    ``kind``: e.g. ``odom_jump``, ``register``, ``relocalise``, ``prior_added``,
    ``prior_rejected``, ``prior_removed``, ``loop_closure``, ``batch_optimised``. A decision that
    accepts or rejects something (a registration, a relocalisation) has ``data["accepted"]``.
    """

    stamp: float
    kind: str
    message: str
    keyframe: int | None = None
    data: dict[str, Any] = field(default_factory=dict)

    @property
    def accepted(self) -> bool | None:
        """``data["accepted"]`` when the decision accepted or rejected something, else None."""
        return self.data.get("accepted")


class DecisionLog(Sequence[DecisionEvent]):
    """The run's decisions in order (a read-only sequence; :meth:`record` appends one).

    ``now``: the stamp of an event recorded without one (the latest scan's; nan before any).
    """

    def __init__(self, now: Callable[[], float] = lambda: float("nan")) -> None:
        self._events: list[DecisionEvent] = []
        self._now = now

    def record(
        self, kind: str, message: str, stamp: float | None = None, keyframe: int | None = None, **data: Any
    ) -> DecisionEvent:
        """Append one decision; returns it."""
        ev = DecisionEvent(
            float(self._now() if stamp is None else stamp), kind, message, keyframe, dict(data)
        )
        self._events.append(ev)
        return ev

    def events(self, kind: str | None = None) -> list[DecisionEvent]:
        """The events of one kind (all with None), in order."""
        return [e for e in self._events if kind is None or e.kind == kind]

    @overload
    def __getitem__(self, i: int) -> DecisionEvent: ...
    @overload
    def __getitem__(self, i: slice) -> list[DecisionEvent]: ...
    def __getitem__(self, i: int | slice) -> DecisionEvent | list[DecisionEvent]:
        return self._events[i]

    def __len__(self) -> int:
        return len(self._events)

    def __iter__(self) -> Iterator[DecisionEvent]:
        return iter(self._events)

    def __repr__(self) -> str:
        return f"DecisionLog({len(self._events)} events)"


__all__ = ["PRIOR_REMOVAL_CAUSES", "DecisionEvent", "DecisionLog", "PriorRemoval"]
