"""The LMI solves of Theorem 1's region under the paper's rule, kept on disk once made.

``allowable_region(loop, "paper")`` solves ``min_condition_P`` at 49 + 8 values of phi_0 and
phi_1 (about half a second): what ``testbed report`` (``losses_as_dos``) and ``testbed analyze``
ask of every scenario.  Their results depend on the matrices Phi_0, Phi_1, the grids and the
solver's code only, so they are kept in ``$TESTBED_CACHE_DIR/regions`` (beside the kernels,
``testbed.sim.kernelcache.cache_dir``) under a hash of exactly those: the same question gets
the same numbers, read back bit for bit.  A changed solver (its source files), another numpy or
Python changes the hash.  A cache that cannot be read or written is skipped: the solves run.
"""

from __future__ import annotations

import hashlib
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:

    pass

#: the modules whose code computes the solves (their source enters the hash)
_SOURCES = ("lmi.py", "theorem1.py", "region.py", "regioncache.py")


def _dir() -> Path:
    from ..sim.kernelcache import cache_dir

    return cache_dir().parent / "regions"


def _key(Phi0: np.ndarray, g0: np.ndarray, Phi1: np.ndarray, g1: np.ndarray) -> str:
    h = hashlib.sha256()
    here = Path(__file__).resolve().parent
    for name in _SOURCES:
        h.update((here / name).read_bytes())
    h.update(f"{np.__version__} {sys.version}".encode())
    for a in (Phi0, g0, Phi1, g1):
        a = np.ascontiguousarray(a, dtype=np.float64)
        h.update(repr(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def paper_solves(Phi0: np.ndarray, g0: np.ndarray, Phi1: np.ndarray, g1: np.ndarray,
                 solve: Callable[[np.ndarray, float], tuple[np.ndarray, float]]) -> tuple[list, list, list, list]:
    """``solve(Phi, phi)`` (``theorem1.min_condition_P``) at every phi_0 of ``g0`` and phi_1 of ``g1``:
    (P0s, k0, P1s, k1), from the cache when it holds them, else solved and stored."""
    try:
        path = _dir() / f"{_key(Phi0, g0, Phi1, g1)}.npz"
    except OSError:
        path = None
    if path is not None and path.is_file():
        try:
            with np.load(path) as z:
                P0, k0, P1, k1 = z["P0"], z["k0"], z["P1"], z["k1"]
            if len(k0) == len(g0) and len(k1) == len(g1):
                return list(P0), [float(v) for v in k0], list(P1), [float(v) for v in k1]
        except Exception:  # noqa: BLE001 - a damaged entry: solved again (and rewritten)
            pass
    P0s, k0 = zip(*(solve(Phi0, p) for p in g0))
    P1s, k1 = zip(*(solve(Phi1, p) for p in g1))
    if path is not None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
            with os.fdopen(fd, "wb") as f:
                np.savez(f, P0=np.array(P0s), k0=np.array(k0), P1=np.array(P1s), k1=np.array(k1))
            os.replace(tmp, path)
        except OSError:
            pass
    return list(P0s), list(k0), list(P1s), list(k1)
