"""Fewer passes of Python's cyclic garbage collector while a post-mortem starts numba and reads a recording.

Importing numba and loading its registries makes about 120,000 objects that live as long as the process.  With
Python's default threshold (a pass of the youngest generation every 700 new objects, and a full pass every hundred
or so of those) every full pass walks them all again.  A post-mortem's data are numpy arrays, freed by their
reference counts, so the cyclic garbage it leaves meanwhile is small.  Figures: docs/benchmarks.md, "Post-mortems
against the disk".
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager

#: new objects between two passes of the youngest generation (Python's default: 700)
THRESHOLD = 50_000


def _raised(old: tuple[int, ...]) -> tuple[int, ...]:
    return (max(old[0], THRESHOLD), *old[1:])


def raise_threshold() -> None:
    """For the rest of the process: a command's own process (``testbed.cli``: the post-mortem commands)."""
    gc.set_threshold(*_raised(gc.get_threshold()))


@contextmanager
def fewer_passes() -> Iterator[None]:
    """For one call in the caller's process (``testbed.open``): the caller's threshold is put back after it."""
    old = gc.get_threshold()
    gc.set_threshold(*_raised(old))
    try:
        yield
    finally:
        gc.set_threshold(*old)
