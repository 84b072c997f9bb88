"""A small dense LMI solver (log-barrier + Newton), enough for the n <= 4 problems of Theorem 1.

cvxpy is not a dependency, and the semidefinite programs of the analysis are tiny
(a handful of symmetric n x n unknowns), so this module solves them directly:

    minimize    c' z
    subject to  G_j(z) = G_j0 + sum_i z_i G_ji  > 0      (each block j, symmetric)

by the barrier method (Boyd and Vandenberghe, Convex Optimization, Sec. 11.3):
for tau = tau_0, 10 tau_0, ... minimize  tau c'z - sum_j log det G_j(z)  by damped
Newton steps from a strictly feasible point; the gradient and Hessian of
-log det G are  -tr(G^{-1} G_i)  and  tr(G^{-1} G_i G^{-1} G_k).  Every iterate stays
strictly feasible (checked with a Cholesky factorization), so whatever point is
returned satisfies the strict inequalities; callers evaluate their constants from
that point and verify them, the optimization only has to be good, not exact.

``max_margin`` is the phase-I problem (largest t with G_j(x) >= t I), used for
feasibility tests in bisections.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


# ----------------------------------------------------------------------------- symmetric bases
def sym_basis(n: int) -> np.ndarray:
    """Basis of the symmetric n x n matrices, shape (n (n + 1) / 2, n, n).

    Element (i, j), i <= j, is E_ii for i == j and E_ij + E_ji otherwise.
    """
    out = []
    for i in range(n):
        for j in range(i, n):
            E = np.zeros((n, n))
            E[i, j] = 1.0
            E[j, i] = 1.0
            out.append(E)
    return np.array(out)


def sym_from_vec(v: np.ndarray, n: int) -> np.ndarray:
    """Symmetric matrix sum_i v_i S_i for the basis of :func:`sym_basis`."""
    return np.tensordot(np.asarray(v, dtype=float), sym_basis(n), axes=1)


def vec_from_sym(P: np.ndarray) -> np.ndarray:
    """Inverse of :func:`sym_from_vec` (upper triangle, row by row)."""
    n = P.shape[0]
    return np.array([P[i, j] for i in range(n) for j in range(i, n)])


# ----------------------------------------------------------------------------- blocks
@dataclass(frozen=True)
class Block:
    """One LMI block G(z) = G0 + sum_i z_i G[i] (all symmetric, m x m)."""

    G0: np.ndarray      # (m, m)
    G: np.ndarray       # (d, m, m)

    def at(self, z: np.ndarray) -> np.ndarray:
        return self.G0 + np.tensordot(z, self.G, axes=1)


def _merge(blocks: Sequence[Block]) -> Block:
    """All blocks as one block-diagonal LMI (one Cholesky per evaluation)."""
    if len(blocks) == 1:
        return blocks[0]
    sizes = [b.G0.shape[0] for b in blocks]
    m = sum(sizes)
    d = blocks[0].G.shape[0]
    G0 = np.zeros((m, m))
    G = np.zeros((d, m, m))
    o = 0
    for b, k in zip(blocks, sizes):
        G0[o:o + k, o:o + k] = b.G0
        G[:, o:o + k, o:o + k] = b.G
        o += k
    return Block(G0, G)


def _chol(M: np.ndarray) -> np.ndarray | None:
    if not np.all(np.isfinite(M)):
        return None
    try:
        return np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        return None


@dataclass
class BarrierResult:
    z: np.ndarray
    value: float        # c'z at the returned (strictly feasible) point
    gap: float          # duality-gap bound m / tau of the last centering
    newton_steps: int
    stopped_early: bool = False


def barrier_minimize(c: np.ndarray, blocks: Sequence[Block], z0: np.ndarray, *, tau0: float | None = None,
                     growth: float = 20.0, rtol: float = 1e-7,
                     atol: float = 1e-10, max_outer: int = 40, max_newton: int = 60,
                     stop_below: float | None = None, stop_if_bound_above: float | None = None) -> BarrierResult:
    """Minimize c'z subject to the strict LMIs ``blocks`` from the strictly feasible z0.

    Parameters
    ----------
    c : (d,) objective.
    blocks : list of :class:`Block` (merged internally into one block-diagonal LMI).
    z0 : (d,) strictly feasible start (raises ValueError otherwise).
    tau0, growth : barrier weight schedule tau_{l+1} = growth * tau_l; tau0
        defaults to m / max(1, |c'z0|) (m = total block size).
    rtol, atol : stop when the barrier's duality-gap bound m / tau is below
        atol + rtol |c'z|.
    stop_below : stop as soon as c'z < stop_below (phase I: a strictly feasible
        point has been found).
    stop_if_bound_above : stop as soon as the certified lower bound c'z - m / tau
        of the optimum (after a centering) exceeds this value (phase I: infeasible).

    Returns
    -------
    BarrierResult with a strictly feasible z.
    """
    c = np.asarray(c, dtype=float)
    z = np.asarray(z0, dtype=float).copy()
    blk = _merge(blocks)
    G0, Gs = blk.G0, blk.G
    d, m_tot = Gs.shape[0], G0.shape[0]
    Gf = Gs.reshape(d, m_tot * m_tot)

    def G_at(v: np.ndarray) -> np.ndarray:
        return G0 + (v @ Gf).reshape(m_tot, m_tot)

    Lc = _chol(G_at(z))
    if Lc is None:
        raise ValueError("barrier_minimize: the starting point is not strictly feasible")
    tau = m_tot / max(1.0, abs(float(c @ z))) if tau0 is None else tau0
    steps = 0
    for _outer in range(max_outer):
        for _ in range(max_newton):
            Linv = np.linalg.inv(Lc)
            Ginv = Linv.T @ Linv
            Y = np.matmul(Ginv, Gs)                           # G^{-1} G_i
            g = tau * c - Gf @ Ginv.ravel()                   # tr(G^{-1} G_i), G symmetric
            H = Y.reshape(d, -1) @ Y.transpose(0, 2, 1).reshape(d, -1).T
            try:
                dz = -np.linalg.solve(H, g)
            except np.linalg.LinAlgError:
                dz = -np.linalg.lstsq(H, g, rcond=None)[0]
            lam2 = float(-g @ dz)            # Newton decrement squared
            if not np.isfinite(lam2) or lam2 / 2.0 < 1e-10:
                break
            # largest step keeping G + s dG > 0: s < 1 / lambda_max(-L^{-1} dG L^{-T})
            dG = (dz @ Gf).reshape(m_tot, m_tot)
            w = np.linalg.eigvalsh(-Linv @ dG @ Linv.T)[-1]
            s = 1.0 if w <= 0 else min(1.0, 0.99 / w)
            f0 = tau * float(c @ z) - 2.0 * np.sum(np.log(np.diag(Lc)))
            while s > 1e-14:
                zn = z + s * dz
                Ln = _chol(G_at(zn))
                if Ln is not None:
                    fn = tau * float(c @ zn) - 2.0 * np.sum(np.log(np.diag(Ln)))
                    if fn <= f0 - 0.25 * s * lam2:
                        break
                s *= 0.5
            else:
                break
            z, Lc = zn, Ln
            steps += 1
            if stop_below is not None and float(c @ z) < stop_below:
                return BarrierResult(z, float(c @ z), m_tot / tau, steps, True)
        gap = m_tot / tau
        if stop_if_bound_above is not None and float(c @ z) - gap > stop_if_bound_above:
            return BarrierResult(z, float(c @ z), gap, steps, True)
        if gap < atol + rtol * abs(float(c @ z)):
            break
        tau *= growth
    return BarrierResult(z, float(c @ z), m_tot / tau, steps, False)


def max_margin(blocks: Sequence[Block], x0: np.ndarray, *, stop_at: float | None = 0.0, rtol: float = 1e-6,
               atol: float = 1e-9) -> tuple[np.ndarray, float]:
    """Phase I: maximize t subject to G_j(x) - t I > 0 for every block.

    The problem must be bounded (normalize homogeneous unknowns, e.g. by a trace).
    With ``stop_at`` set, stop as soon as t > stop_at (a strictly feasible point of
    the original LMIs when stop_at >= 0) or as soon as the duality gap certifies
    max t <= stop_at (then the returned t is below stop_at).  Returns (x, t).
    """
    x0 = np.asarray(x0, dtype=float)
    t0 = min(float(np.linalg.eigvalsh(b.at(x0))[0]) for b in blocks) - 1.0
    aug = []
    for b in blocks:
        mdim = b.G0.shape[0]
        aug.append(Block(b.G0, np.concatenate([b.G, -np.eye(mdim)[None]], axis=0)))
    c = np.zeros(x0.shape[0] + 1)
    c[-1] = -1.0
    res = barrier_minimize(c, aug, np.append(x0, t0), rtol=rtol, atol=atol,
                           stop_below=None if stop_at is None else -stop_at,
                           stop_if_bound_above=None if stop_at is None else -stop_at)
    return res.z[:-1], float(res.z[-1])
