"""Real-time testbed for linearization-based quantized control under DoS attacks.

``testbed.open(PATH)`` and ``testbed.simulate(SCENARIO, **overrides)`` return a
``testbed.api.Run`` (see docs/api.md).  They are imported on first use, so
``import testbed`` stays cheap (no numba, zenoh or mcap).

``testbed.simulate`` is also the name of the simulator's module: the attribute
is a callable that runs :func:`testbed.api.simulate` and otherwise reads
through to the module (``testbed.simulate.simulate_scenario`` still works, and
``from testbed.simulate import ...`` is untouched).
"""

import sys
import types

__version__ = "0.1.0"


class _Simulate:
    """``testbed.simulate(scenario, **overrides)`` -> ``Run``; attributes read through to the module."""

    def __call__(self, scenario, **overrides):
        from .api import simulate

        return simulate(scenario, **overrides)

    def __getattr__(self, name):
        import importlib

        return getattr(importlib.import_module(f"{__name__}.simulate"), name)

    def __repr__(self) -> str:
        return "<testbed.simulate: testbed.api.simulate, and the module testbed/simulate.py>"


class _Package(types.ModuleType):
    simulate = property(lambda self: _SIMULATE, lambda self, module: None)  # the import system's setattr

    def __getattr__(self, name):
        if name in ("open", "Run"):
            from . import api

            return getattr(api, name)
        raise AttributeError(f"module 'testbed' has no attribute {name!r}")

    def __dir__(self):
        return sorted([*self.__dict__, "open", "simulate", "Run"])


_SIMULATE = _Simulate()
sys.modules[__name__].__class__ = _Package
