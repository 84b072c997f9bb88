"""The run's faults as the launcher gathers them: every collaborator appends its ``Fault`` here, and the
launcher publishes each new one once, as an ``Event`` of node ``launcher`` (so the recording has it)."""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from typing import TYPE_CHECKING

from ..record.faults import Fault, given
from ..wire import messages as msg

if TYPE_CHECKING:
    import zenoh


class FaultLog:
    """The run's faults in the order they happened, and how many of them the recording has."""

    def __init__(self) -> None:
        self._faults: list[Fault] = []
        self._published = 0

    def append(self, f: Fault) -> None:
        self._faults.append(f)

    def extend(self, fs: Iterable[Fault]) -> None:
        self._faults.extend(fs)

    def __iter__(self) -> Iterator[Fault]:
        return iter(self._faults)

    def __len__(self) -> int:
        return len(self._faults)

    def any(self, kind: str) -> bool:
        return any(f.kind == kind for f in self._faults)

    def dicts(self) -> list[dict]:
        """The written form (the summary's ``faults``)."""
        return [f.to_dict() for f in self._faults]

    def publish(self, session: zenoh.Session, key: str) -> None:
        """Each new fault as an ``Event`` of node ``launcher`` on ``key``: kind ``<node>_<kind>``, its sample
        (-1 without one), its written form as JSON in ``detail``."""
        while self._published < len(self._faults):
            f = self._faults[self._published]
            self._published += 1
            k = given(f.sample)
            e = msg.Event(node="launcher", kind=f"{given(f.role) or 'run'}_{f.kind}",
                          k=-1 if k is None else int(k), detail=json.dumps(f.to_dict(), default=str))
            try:
                session.put(key, e.encode())
            except Exception:  # noqa: BLE001 - the session may be closing
                pass


__all__ = ["FaultLog"]
