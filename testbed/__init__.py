"""Real-time testbed for linearization-based quantized control under DoS attacks.

The Python API (docs/api.md), imported on first use so that ``import testbed`` stays cheap
(no numba, zenoh or mcap):

* ``testbed.open(PATH)`` and ``testbed.simulate(SCENARIO, **overrides)`` return a
  ``testbed.Run`` (``testbed.api.Run``: arrays, summary, ``save``, ``plot``, data frames);
* ``testbed.compare(A, B)``: two runs compared sample by sample (the dict of
  ``testbed compare --json``);
* ``testbed.BadInput``: what every bad argument raises (one line that says what to change).

``testbed.simulate`` and ``testbed.compare`` are also the names of modules: the attribute
is a callable that otherwise reads through to its module (``testbed.simulate.simulate_scenario``
and ``testbed.compare.compare`` work, and ``from testbed.simulate import ...`` is untouched).
"""

import sys
import types

from .errors import BadInput

__version__ = "0.1.0"
__all__ = ["BadInput", "__version__"]  # and, on first use: open, simulate, compare, Run


class _Entry:
    """A function of the API that reads through to the module of the same name."""

    def __init__(self, module: str, api: str, doc: str):
        self._module, self._api = module, api
        self.__doc__ = doc

    def __call__(self, *args, **kwargs):
        import importlib

        mod, _, name = self._api.rpartition(".")
        return getattr(importlib.import_module(f"{__name__}.{mod}"), name)(*args, **kwargs)

    def __getattr__(self, name):
        import importlib

        if name.startswith("__"):
            raise AttributeError(name)
        return getattr(importlib.import_module(f"{__name__}.{self._module}"), name)

    def __repr__(self) -> str:
        return f"<testbed.{self._module}: testbed.{self._api}, and the module testbed/{self._module}.py>"


_SIMULATE = _Entry("simulate", "api.simulate",
                   "testbed.simulate(scenario, **overrides) -> Run (testbed.api.simulate)")
_COMPARE = _Entry("compare", "compare.compare",
                  "testbed.compare(a, b) -> dict: two runs (recordings, scenarios or Runs) compared sample by sample")


class _Package(types.ModuleType):
    # the import system sets the submodule as an attribute after ``import testbed.simulate``: ignored
    simulate = property(lambda self: _SIMULATE, lambda self, module: None)
    compare = property(lambda self: _COMPARE, lambda self, module: None)

    def __getattr__(self, name):
        if name in ("open", "Run"):
            from . import api

            return getattr(api, name)
        raise AttributeError(f"module 'testbed' has no attribute {name!r}")

    def __dir__(self):
        return sorted([*self.__dict__, "open", "simulate", "compare", "Run", "BadInput"])


sys.modules[__name__].__class__ = _Package
