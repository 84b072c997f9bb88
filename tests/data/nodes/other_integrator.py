"""A healthy plant that is not the testbed's bit for bit, for the conformance tests: the bundled plant node
with its flow map phi_T replaced by scipy's ``solve_ivp`` (RK45 at rtol 1e-12, atol 1e-14) on the Lienard
equations written out here (docs/plants-and-quantizer.md), as a device with its own integrator would.
Its steps stay within about 1e-10 of the model's; its states differ from the simulator's from sample 1 on.

``python other_integrator.py`` joins the run of ``$TESTBED_JOIN`` as ``testbed node plant`` does."""

from __future__ import annotations

import sys

import numpy as np
from scipy.integrate import solve_ivp

from testbed.common.dispatch import run_child
from testbed.loop.protocol import FLOW_OK, OdeProcess


def _advance(self, u, dt: float) -> int:
    if dt <= 0.0:
        return FLOW_OK
    if self.plant.name != "lienard":
        raise SystemExit(f"other_integrator.py: the Lienard plant only, not {self.plant.name}")
    a, b = (float(v) for v in self.plant.param_vector())
    u0 = float(np.asarray(u, dtype=float).reshape(-1)[0])

    def f(_t, x):
        x1 = x[0]
        return [x[1] + x1 + a * x1 ** 3 - b * x1 ** 5, -x1 + u0]

    sol = solve_ivp(f, (0.0, float(dt)), self._x, method="RK45", rtol=1e-12, atol=1e-14)
    self._x = np.array(sol.y[:, -1], dtype=np.float64)
    return FLOW_OK


def main() -> int:
    OdeProcess.advance = _advance
    return run_child(["node", "plant"])


if __name__ == "__main__":
    sys.exit(main())
