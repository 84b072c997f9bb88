"""The phase plane that the Rerun and the Foxglove views share: its axes, its bounds, the outline
of the nominal region of attraction.

The phase plane shows components ``PHASE_DIMS`` of the state; for n > 2 (the cart-pole) it is a
projection and no region-of-attraction outline is drawn (the region is a 4-D set; its grid is a
slice over other coordinates).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..scenario import Scenario

#: the components of x drawn as the phase plane's axes
PHASE_DIMS = (0, 1)


@dataclass(frozen=True)
class RoaOutline:
    """Outline of the nominal region of attraction in the phase plane (``lines``: list of (P, 2))."""

    lines: tuple
    window: tuple          # ((x_lo, x_hi), (y_lo, y_hi)) of the grid
    fraction: float        # of the grid inside
    note: str


def roa_outline(sc: Scenario, grid: int = 61) -> RoaOutline | None:
    """The nominal region's outline (level 1/2 of the grid's membership), None for n != 2.

    A coarse grid (61 x 61: under a second for the paper's plant) is enough for a picture.
    """
    plant = sc.make_model()
    if plant.n != 2:
        return None
    key = (sc.source or sc.name, tuple(np.asarray(sc.K).ravel()), float(sc.T), int(grid))
    return _roa_for(key, sc, grid)


_ROA_CACHE: dict = {}


def _roa_for(key: tuple, sc: Scenario, grid: int) -> RoaOutline:
    if key in _ROA_CACHE:
        return _ROA_CACHE[key]
    import contourpy

    from ..analysis.roa import nominal_roa

    r = nominal_roa(sc.make_model(), sc.K, sc.T, grid=grid, flow=sc.flow)
    window = ((float(r.xs[0]), float(r.xs[-1])), (float(r.ys[0]), float(r.ys[-1])))
    if r.inside.all():
        (x0, x1), (y0, y1) = window
        lines: tuple[np.ndarray, ...] = (np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]),)
        note = "the whole gridded window is inside the nominal region"
    else:
        gen = contourpy.contour_generator(r.xs, r.ys, r.inside.astype(float))
        lines = tuple(np.asarray(ln) for ln in gen.lines(0.5) if len(ln) >= 2)
        note = f"nominal region of attraction, {len(r.xs)}x{len(r.ys)} grid"
    out = RoaOutline(lines, window, r.fraction, note)
    _ROA_CACHE[key] = out
    return out


def phase_bounds(sc: Scenario, x: np.ndarray | None = None,
                 roa: RoaOutline | None = None) -> tuple[tuple[float, float], tuple[float, float]]:
    """Visual bounds of the phase plane: around the trajectory when known (offline), else around the origin and x0."""
    a, b = PHASE_DIMS
    if x is None:  # live: a window around the origin that holds x0 and reaches the nearest part of the ROA outline
        r = 3.5 * float(np.max(np.abs(np.asarray(sc.x0, dtype=float)[[a, b]]))) or 1.0
        if roa is not None and roa.lines:
            r = max(r, 1.2 * min(float(np.min(np.max(np.abs(ln), axis=1))) for ln in roa.lines))
        return ((-r, r), (-r, r))
    pts = np.asarray(sc.x0, dtype=float)[[a, b]][None, :]
    if len(x):
        pts = np.vstack([pts, np.asarray(x, dtype=float)[:, [a, b]]])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = np.maximum(0.5 * (hi - lo), 0.5 * np.max(np.abs(pts)) + 1e-3)
    return ((float(lo[0] - pad[0]), float(hi[0] + pad[0])), (float(lo[1] - pad[1]), float(hi[1] + pad[1])))
