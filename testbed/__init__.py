"""Real-time testbed for linearization-based quantized control under DoS attacks.

The Python API (docs/api.md), imported on first use so that ``import testbed`` stays cheap
(no numba, zenoh or mcap):

* ``testbed.open(PATH)`` and ``testbed.simulate(SCENARIO, **overrides)`` return a
  ``testbed.Run`` (``testbed.runs.run``: arrays, summary, ``save``, ``plot``, data frames);
* ``testbed.compare(A, B)``: two runs compared sample by sample (the dict of
  ``testbed compare --json``; ``testbed.runs.compare``);
* ``testbed.BadInput``: what every bad argument raises (one line that says what to change).
"""

from typing import Any as _Any

from .common.errors import BadInput

__version__ = "0.1.0"
__all__ = ["BadInput", "__version__"]  # and, on first use: open, simulate, compare, Run (not in *: open)

#: the API's names imported on first use: name -> (module under testbed, attribute)
_LAZY = {"open": ("runs.run", "open"), "simulate": ("runs.run", "simulate"), "Run": ("runs.run", "Run"),
         "compare": ("runs.compare", "compare")}


def __getattr__(name: str) -> _Any:
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(f"{__name__}.{module}"), attr)
    raise AttributeError(f"module 'testbed' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])
