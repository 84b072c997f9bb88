"""How the device's integrator step was chosen: classical RK4 with s equal substeps over one period T,
as devices/pico-plant/src/plant.c computes it, against the testbed's flow map phi_T (DOP853 at
rtol 1e-11, atol 1e-13) on random (x, u) of the Lienard plant, for growing boxes of states and inputs.

    python devices/pico-plant/step_error.py [--T 0.1] [--points 4000]

Prints the max |RK4 - phi_T| per box and number of substeps (docs/devices.md quotes it).
"""

from __future__ import annotations

import argparse

import numpy as np

from plants.lienard import Lienard
from testbed.loop.flow import phi_T


def rk4(plant: Lienard, x: np.ndarray, u: np.ndarray, T: float, substeps: int) -> np.ndarray:
    """The device's integrator, vectorised: the same operations in the same order as plant.c."""
    a, b = plant.a, plant.b

    def f(y):
        x1 = y[:, 0]
        x1sq = x1 * x1
        return np.stack([y[:, 1] + x1 + a * x1 * x1sq - b * x1 * x1sq * x1sq, -x1 + u[:, 0]], axis=1)

    h = T / substeps
    for _ in range(substeps):
        k1 = f(x)
        k2 = f(x + 0.5 * h * k1)
        k3 = f(x + 0.5 * h * k2)
        k4 = f(x + h * k3)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return x


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--T", type=float, default=0.1)
    ap.add_argument("--points", type=int, default=4000)
    args = ap.parse_args()
    plant, rng = Lienard(), np.random.default_rng(1)
    print("| box | " + " | ".join(f"{s} substeps" for s in (5, 10, 20, 50, 100, 200)) + " |")
    print("|---" * 7 + "|")
    for r, ur in ((0.5, 2.0), (1.5, 5.0), (2.5, 10.0)):
        x = rng.uniform(-r, r, (args.points, 2))
        u = rng.uniform(-ur, ur, (args.points, 1))
        ref, status = phi_T(plant, x, u, args.T)
        assert not status.any()
        errs = [np.abs(rk4(plant, x, u, args.T, s) - ref).max() for s in (5, 10, 20, 50, 100, 200)]
        print(f"| abs(x) <= {r}, abs(u) <= {ur} | " + " | ".join(f"{e:.1e}" for e in errs) + " |")


if __name__ == "__main__":
    main()
