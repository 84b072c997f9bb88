"""Forward-or-drop decision of a live DoS proxy (pure, no I/O).

A :class:`Gate` sits on the sensor-to-controller channel and decides, for the
packet sent at ``t_k = k T``, whether it is dropped (``theta_k = 1``) or
forwarded (``theta_k = 0``).  It is driven either by an offline
:class:`~attackers.schedule.Schedule` or by an online
:class:`~attackers.greedy.GreedyAttacker`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from .checks import field
from .schedule import Schedule, sample_eps

if TYPE_CHECKING:  # numba: imported only for an online (greedy) gate
    from .greedy import GreedyAttacker

__all__ = ["Gate"]


def _is_greedy(source: object) -> bool:
    from .greedy import GreedyAttacker

    return isinstance(source, GreedyAttacker)


class Gate:
    """Drop packets according to a DoS schedule (offline) or a greedy attacker (online).

    ``Gate(source, T=None)``: ``source`` is a :class:`Schedule` or a
    :class:`GreedyAttacker`.  For a schedule, pass the sampling period ``T`` to
    use exactly the membership tolerance of :meth:`Schedule.theta_samples`
    (``eps = 1e-9 T``); without it a tiny relative tolerance is used
    (see :meth:`Schedule.theta`).  For a greedy attacker ``T`` is taken from it.

    Counters: ``forwarded``, ``dropped`` (packets so far), ``attack_on`` (status
    after the last decision), ``attacks_started`` (rising edges of ``theta``).
    """

    def __init__(self, source: Any, T: float | None = None) -> None:
        if isinstance(source, Schedule):
            self.mode = "schedule"
        elif _is_greedy(source):
            self.mode = "greedy"
            if T is None:
                T = source.T
            elif not math.isclose(float(T), source.T, rel_tol=1e-12, abs_tol=0.0):
                raise ValueError(f"Gate: T={T!r} differs from the greedy attacker's T={source.T!r}")
        else:
            raise ValueError(
                f"Gate source must be a Schedule or a GreedyAttacker, got {type(source).__name__}"
            )
        if T is not None:
            T = field("Gate: sampling period T", T, lo=0.0, lo_open=True)
        self.source = source
        self.T = T
        self._eps = sample_eps(T) if T is not None else None
        self.forwarded = 0
        self.dropped = 0
        self.attack_on = False
        self.attacks_started = 0

    @classmethod
    def from_schedule(cls, schedule: Schedule, T: float | None = None) -> "Gate":
        return cls(schedule, T)

    @classmethod
    def from_greedy(cls, attacker: GreedyAttacker) -> "Gate":
        return cls(attacker)

    @property
    def is_online(self) -> bool:
        return self.mode == "greedy"

    def theta(self, k: int, t_k: float, score: float = 0.0) -> int:
        """``theta_k`` without touching the counters (the greedy state does advance)."""
        if self.mode == "schedule":
            return self.source.theta(float(t_k), eps=self._eps)
        return self.source.decide(int(k), float(score))

    def decide(self, k: int, t_k: float, score: float = 0.0) -> bool:
        """Return ``True`` to drop the packet of sample ``k`` sent at ``t_k`` (``theta_k = 1``).

        ``score`` feeds the greedy attacker (e.g. ``||x_k||_inf`` or ``E_k``) and is
        ignored by a schedule.  Updates ``forwarded`` / ``dropped`` / ``attack_on``.
        """
        drop = bool(self.theta(k, t_k, score))
        if drop:
            self.dropped += 1
            if not self.attack_on:
                self.attacks_started += 1
        else:
            self.forwarded += 1
        self.attack_on = drop
        return drop

    def reset(self) -> None:
        """Zero the counters (and the greedy attacker's budget)."""
        self.forwarded = 0
        self.dropped = 0
        self.attack_on = False
        self.attacks_started = 0
        if self.mode == "greedy":
            self.source.reset()

    def __repr__(self) -> str:
        return (
            f"Gate(mode={self.mode!r}, forwarded={self.forwarded}, dropped={self.dropped}, "
            f"attack_on={self.attack_on})"
        )
