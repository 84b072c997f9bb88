"""The resilient dynamic quantizer: Algorithms 1 and 2, update rules (xi) and (E).

The quantization region is the hypercube Q(xi_k, E_k) = {x : ||x - xi_k||_inf <= E_k},
split into M^n equal boxes indexed by the integers {0, ..., M^n - 1}; coordinate j
has cell index c_j in {0, ..., M-1} and the symbol is i = sum_j c_j M^j.  The
decoder's q_k is the centre of the box, so ||x_k - q_k||_inf <= E_k / M (4).

After every sample both ends apply, from (theta_k, the symbol) alone,

    xi_{k+1} = phi_T(q_k, K q_k)   if theta_k = 0        (xi)
               phi_T(xi_k, 0)      if theta_k = 1
    E_{k+1}  = (Lambda / M) E_k    if theta_k = 0        (E)
               Lambda E_k          if theta_k = 1

with Lambda = e^{L T}.  The encoder learns theta_k from the decoder's ack.

Saturation.  In a real loop x_k does leave Q(xi_k, E_k) (round-off once E_k is
~1e-13 of the state, model mismatch, late inputs).  Two modes:

* ``ideal`` (the paper): the encoder clips x_k to the nearest box and sends its
  index; the event is counted.  Nothing else changes.
* ``resilient`` (default): the encoder sends the spare OVERFLOW codeword M^n
  instead.  A decoder that receives it applies u_k = 0 and both ends zoom out:
  xi_{k+1} = phi_T(xi_k, 0), E_{k+1} = sigma * Lambda * max(E_k, E_r), with sigma >= 1
  (``zoom_out``, default M) and the rescue radius E_r = 1e-9 (1 + ||xi_k||_inf), so
  that a range that underflowed to 0 in a long run can grow again.  If the OVERFLOW packet itself is lost, both ends
  apply the ordinary theta_k = 1 rule, so they stay in lockstep: the update
  depends only on what both know (theta_k and, when theta_k = 0, the symbol).
  The encoder retries at the next sample while x stays outside.  Optionally
  E_{k+1} = max(E_{k+1}, E_min) (both ends), a floor that keeps E above the
  round-off level at the price of convergence to a ball of radius ~E_min / M.

Symbols are packed big-endian into ceil(bits / 8) bytes, where bits is the
number of bits of the largest code: ceil(n log2 M) in the ideal mode and
ceil(log2(M^n + 1)) in the resilient mode (the same unless M^n is a power of two).
Unpacking rejects a wrong length or a code outside the codebook.

This module holds the pure kernels.  The ends that run them, the paper's method written
against the method interface like every other, are ``testbed.methods.paper``
(``PaperEncoder``, ``PaperDecoder``).
"""

from __future__ import annotations

import math
from typing import Any

import numba as nb
import numpy as np

from .flow import flow_into
from .params import (  # noqa: F401 - the quantizer's public names
    MAX_CODES,
    MODE_IDEAL,
    MODE_NONE,
    MODE_RESILIENT,
    MODES,
    ROUNDOFF,
    RULES,
    Codebook,
    CodebookTooLarge,
    InvalidSymbol,
    QuantizerParams,
    delay_margin_gain,
)


# ----------------------------------------------------------------------------- pure kernels
@nb.njit(cache=True)
def quantize_index(x: np.ndarray, xi: np.ndarray, E: float, M: int) -> tuple[int, bool]:
    """Algorithm 1, one sample: symbol of the box of Q(xi, E) containing x.

    Returns (i, saturated): saturated is True when x is outside Q(xi, E); then i is
    the index of the nearest box (coordinates clipped).
    """
    n = x.shape[0]
    idx = 0
    mult = 1
    sat = False
    for j in range(n):
        d = x[j] - xi[j]
        if E > 0.0:
            if abs(d) > E or d != d:
                sat = True
            s = (d + E) / (2.0 * E) * M
            if s != s:
                c = 0
            elif s < 0.0:
                c = 0
            elif s >= M:
                c = M - 1
            else:
                c = int(math.floor(s))
                if c > M - 1:
                    c = M - 1
        else:
            if d != 0.0:
                sat = True
            c = M // 2
        idx += c * mult
        mult *= M
    return idx, sat


@nb.njit(cache=True)
def box_center(idx: int, xi: np.ndarray, E: float, M: int, out: np.ndarray) -> None:
    """Algorithm 2: q = centre of box ``idx`` of Q(xi, E), written into ``out``."""
    n = xi.shape[0]
    r = idx
    for j in range(n):
        c = r % M
        r //= M
        out[j] = xi[j] - E + (2.0 * c + 1.0) * E / M


@nb.njit(cache=True)
def control_input(Kgain: np.ndarray, q: np.ndarray, theta: int, overflow: bool, u: np.ndarray) -> None:
    """Control law (2): u_k = (1 - theta_k) K q_k; u_k = 0 after an OVERFLOW codeword too."""
    m = Kgain.shape[0]
    n = Kgain.shape[1]
    for r in range(m):
        acc = 0.0
        if theta == 0 and not overflow:
            for j in range(n):
                acc += Kgain[r, j] * q[j]
        u[r] = acc


@nb.njit(cache=True)
def floor_E(En: float, xi_next: np.ndarray, E_min: float) -> float:
    """E_{k+1} never below the round-off of the box arithmetic around xi_{k+1} (a few ulp: a range
    narrower than that cannot hold x_{k+1} however exact the prediction), nor below ``E_min``."""
    big = 0.0
    for i in range(xi_next.shape[0]):
        big = max(big, abs(xi_next[i]))
    if En < ROUNDOFF * big:
        En = ROUNDOFF * big
    if En < E_min:
        En = E_min
    return En


@nb.njit(cache=True)
def zoom_update(rhs: Any, p: np.ndarray, T: float, opts: np.ndarray, Kgain: np.ndarray, theta: int, overflow: bool,
                xi: np.ndarray, E: float, q: np.ndarray, u_prev: np.ndarray, Lambda: float, M: int, sigma: float,
                E_min: float, dpar: np.ndarray, K_s: np.ndarray, ytmp: np.ndarray, u_s: np.ndarray,
                xi_out: np.ndarray) -> tuple[float, int]:
    """Update rules (xi) and (E) (and the OVERFLOW zoom-out). Returns (E_next, flow status).

    ``u_s`` receives u_k, the input both ends know was sent for this sample
    ((1 - theta_k) K q_k, or 0 after OVERFLOW): the caller keeps it as the next ``u_prev``.

    ``dpar`` = [delta_hat_0, g_0, delta_hat_1, g_1]: the delay-aware rule's nominal delay
    and margin gain for a sample whose symbol arrived (theta_k = 0, index 0) and for one
    decided lost at the controller's loss deadline (theta_k = 1, index 1).  All zero: the
    paper's rule, xi_{k+1} = phi_T(q_k, K q_k) or phi_T(xi_k, 0).  Delay-aware rule (an
    extension, docs/paper.md): the plant holds u_{k-1} for the first delta_k of the period,
    so both ends predict with the nominal delay, xi_{k+1} =
    phi_{T - delta_hat}(phi_delta_hat(q_k, u_{k-1}), u_k), and add the margin
    g ||u_k - u_{k-1}||_inf to E_{k+1}, which covers every delay in the declared bound.
    """
    m = u_s.shape[0]
    if theta == 0 and not overflow:
        control_input(Kgain, q, 0, False, u_s)
        start = q
    else:
        for r in range(m):
            u_s[r] = 0.0
        start = xi
    j = 2 if theta == 1 else 0
    delay_hat = dpar[j]
    margin_gain = dpar[j + 1]
    if delay_hat > 0.0:
        st = flow_into(rhs, start, u_prev, p, delay_hat, opts, K_s, ytmp, xi_out)
        if st == 0:  # flow_into may integrate in place (x0 is out): it reads x0 only to copy it
            st = flow_into(rhs, xi_out, u_s, p, T - delay_hat, opts, K_s, ytmp, xi_out)
    else:
        st = flow_into(rhs, start, u_s, p, T, opts, K_s, ytmp, xi_out)
    if theta == 0 and not overflow:
        En = Lambda / M * E
    elif theta == 0:  # OVERFLOW received: zoom out from at least a small rescue radius, so
        # that a range that underflowed to 0 (long runs at small T) can still grow again
        rescue = 0.0
        for i in range(xi.shape[0]):
            rescue = max(rescue, abs(xi[i]))
        rescue = 1e-9 * (1.0 + rescue)
        En = sigma * Lambda * max(E, rescue)
    else:
        En = Lambda * E
    if margin_gain > 0.0:
        du = 0.0
        for r in range(m):
            du = max(du, abs(u_s[r] - u_prev[r]))
        En += margin_gain * du
    return floor_E(En, xi_out, E_min), st

