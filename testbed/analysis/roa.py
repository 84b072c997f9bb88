"""Nominal region of attraction on a grid (the gray area of the paper's third figure).

Nominal means no quantization and no DoS: u_k = K x_k held over each sampling
period, x_{k+1} = phi_T(x_k, K x_k).  A grid state belongs to the region when the
nominal loop started there reaches ||x||_inf < tol within the horizon (the batch
simulator with ``mode="none"``).  For n > 2 a two-dimensional slice is gridded
(``dims``), the other coordinates fixed at ``center``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, cast

import numpy as np

from ..loop.flow import DEFAULT_FLOW, FLOW_OK, FlowOptions
from ..loop.quantizer import QuantizerParams
from .parallel import run_batch

if TYPE_CHECKING:
    import numpy.typing as npt

    from plants.base import Plant

    from .parallel import Executor, Progress

#: default half-widths of the gridded window per plant (covering the Lienard limit cycle)
DEFAULT_WINDOWS = {"lienard": (5.0, 7.0), "pendulum": (math.pi, 2.0 * math.pi), "cartpole": (0.6, 2.0),
                   "linear": (1.0, 1.0)}
#: default gridded coordinates per plant
DEFAULT_DIMS = {"cartpole": (2, 3)}


def default_window(plant: Plant) -> tuple[float, float]:
    return DEFAULT_WINDOWS.get(plant.name, (1.0, 1.0))


def default_dims(plant: Plant) -> tuple[int, int]:
    return DEFAULT_DIMS.get(plant.name, (0, 1))


def state_grid(plant: Plant, grid: int | tuple[int, int], window: tuple[float, float], dims: tuple[int, int],
               center: npt.ArrayLike | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """States of a grid over coordinates ``dims``: (xs, ys, X) with X of shape (ny * nx, n), row-major in y."""
    nx, ny = (grid, grid) if isinstance(grid, (int, float, np.number)) else grid
    wx, wy = window
    c = np.zeros(plant.n) if center is None else np.asarray(center, dtype=float)
    xs = c[dims[0]] + np.linspace(-wx, wx, int(nx))
    ys = c[dims[1]] + np.linspace(-wy, wy, int(ny))
    X = np.tile(c, (len(xs) * len(ys), 1))
    GX, GY = np.meshgrid(xs, ys, indexing="xy")
    X[:, dims[0]] = GX.ravel()
    X[:, dims[1]] = GY.ravel()
    return xs, ys, X


@dataclass
class RoaResult:
    """Nominal region of attraction on a grid: ``inside[iy, ix]`` for the state (xs[ix], ys[iy])."""

    xs: np.ndarray
    ys: np.ndarray
    inside: np.ndarray
    dims: tuple[int, int]
    center: np.ndarray
    horizon: float
    tol: float
    wall: float = 0.0
    traj_steps: int = 0
    status_counts: dict = field(default_factory=dict)

    @property
    def fraction(self) -> float:
        """Fraction of the grid inside the region."""
        return float(self.inside.mean())

    @property
    def area(self) -> float:
        """Area of the region in the gridded plane (cells of the grid, edge cells halved)."""
        dx = (self.xs[-1] - self.xs[0]) / max(len(self.xs) - 1, 1)
        dy = (self.ys[-1] - self.ys[0]) / max(len(self.ys) - 1, 1)
        w = np.ones_like(self.inside, dtype=float)
        w[0, :] *= 0.5
        w[-1, :] *= 0.5
        w[:, 0] *= 0.5
        w[:, -1] *= 0.5
        return float(np.sum(w * self.inside) * dx * dy)

    @property
    def rate(self) -> float:
        """Trajectory-steps per second of the batch simulation."""
        return self.traj_steps / self.wall if self.wall > 0 else math.nan

    def contains(self, X: npt.ArrayLike) -> np.ndarray:
        """Nearest-grid-point lookup of membership for states X (..., n); False outside the window."""
        X = np.asarray(X, dtype=float)
        a, b = X[..., self.dims[0]], X[..., self.dims[1]]
        ix = np.rint((a - self.xs[0]) / (self.xs[1] - self.xs[0])).astype(int)
        iy = np.rint((b - self.ys[0]) / (self.ys[1] - self.ys[0])).astype(int)
        ok = (ix >= 0) & (ix < len(self.xs)) & (iy >= 0) & (iy < len(self.ys))
        out = np.zeros(a.shape, dtype=bool)
        out[ok] = self.inside[iy[ok], ix[ok]]
        return out

    @property
    def digest(self) -> str:
        """sha256 of the inside/outside mask (shape, then one byte per state, row-major in y)."""
        import hashlib

        m = np.ascontiguousarray(self.inside, dtype=np.uint8)
        return "sha256:" + hashlib.sha256(f"{m.shape[0]}x{m.shape[1]}:".encode() + m.tobytes()).hexdigest()

    def to_dict(self) -> dict:
        return {"grid": [len(self.xs), len(self.ys)], "dims": list(self.dims), "inside_digest": self.digest,
                "window": [[float(self.xs[0]), float(self.xs[-1])], [float(self.ys[0]), float(self.ys[-1])]],
                "center": self.center.tolist(), "horizon": self.horizon, "tol": self.tol,
                "fraction_inside": self.fraction, "area": self.area, "wall_s": self.wall,
                "traj_steps": self.traj_steps, "traj_steps_per_s": self.rate, "status_counts": self.status_counts}


def nominal_roa(plant: Plant, K: npt.ArrayLike, T: float, *, grid: int | tuple[int, int] = 201,
                window: tuple[float, float] | None = None, dims: Sequence[int] | None = None,
                center: npt.ArrayLike | None = None, horizon: float = 30.0, tol: float = 1e-4,
                flow: FlowOptions = DEFAULT_FLOW, chunk: int | None = None, progress: Progress | None = None,
                executor: Executor | None = None) -> RoaResult:
    """Grid the nominal region of attraction with the batch simulator.

    Parameters
    ----------
    plant, K, T : the loop (K is m x n, u = K x).
    grid : points per axis (int or (nx, ny)).
    window : half-widths (wx, wy) around ``center`` (default per plant, see ``DEFAULT_WINDOWS``).
    dims : the two gridded coordinates (default (0, 1); (2, 3) for the cart-pole).
    center : the state the window is centred on; fixes the other coordinates (default 0).
    horizon : seconds simulated; tol : convergence radius ||x_N||_inf < tol.
    chunk : trajectories per chunk (default: see ``parallel.chunk_size``); ``progress(done, total)``
        is called per chunk.
    executor : a ``parallel.Executor`` (None: this process); the result does not depend on it.

    Returns
    -------
    RoaResult (with wall time and trajectory-steps).
    """
    window = default_window(plant) if window is None else window
    dims = default_dims(plant) if dims is None else cast("tuple[int, int]", tuple(dims))  # two coordinates
    xs, ys, X = state_grid(plant, grid, window, dims, center)
    n_steps = int(round(horizon / T))
    qp = QuantizerParams(T=T, M=2, L=0.0, E0=1.0, mode="none")
    t0 = time.perf_counter()
    out = run_batch(plant, K, qp, X, n_steps, mode="none", flow=flow, fields=("x_final", "status"),
                    executor=executor, progress=progress, chunk=chunk)
    status = out["status"].astype(np.int64)
    conv = (status == FLOW_OK) & (np.max(np.abs(out["x_final"]), axis=1) < tol)  # BatchResult.converged
    wall = time.perf_counter() - t0
    counts = {int(k): int(v) for k, v in zip(*np.unique(status, return_counts=True))}
    c = np.zeros(plant.n) if center is None else np.asarray(center, dtype=float)
    return RoaResult(xs, ys, conv.reshape(len(ys), len(xs)), dims, c, horizon, tol, wall,
                     X.shape[0] * n_steps, counts)
