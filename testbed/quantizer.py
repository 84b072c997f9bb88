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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from .flow import DEFAULT_FLOW, FlowOptions, flow_into

MODE_IDEAL = 0
MODE_RESILIENT = 1
MODE_NONE = 2  # no quantization at all (q_k = x_k): the nominal loop of the region of attraction
MODES = {"ideal": MODE_IDEAL, "resilient": MODE_RESILIENT, "none": MODE_NONE}


class InvalidSymbol(ValueError):
    """A payload that is not a code of the codebook (wrong length or out of range)."""


# ----------------------------------------------------------------------------- pure kernels
@nb.njit(cache=True)
def quantize_index(x, xi, E, M):
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
def box_center(idx, xi, E, M, out):
    """Algorithm 2: q = centre of box ``idx`` of Q(xi, E), written into ``out``."""
    n = xi.shape[0]
    r = idx
    for j in range(n):
        c = r % M
        r //= M
        out[j] = xi[j] - E + (2.0 * c + 1.0) * E / M


@nb.njit(cache=True)
def control_input(Kgain, q, theta, overflow, u):
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
def zoom_update(rhs, p, T, opts, Kgain, theta, overflow, xi, E, q, Lambda, M, sigma,
                E_min, K_s, ytmp, u_s, xi_out):
    """Update rules (xi) and (E) (and the OVERFLOW zoom-out). Returns (E_next, flow status)."""
    if theta == 0 and not overflow:
        control_input(Kgain, q, 0, False, u_s)
        st = flow_into(rhs, q, u_s, p, T, opts, K_s, ytmp, xi_out)
        En = Lambda / M * E
    else:
        for r in range(u_s.shape[0]):
            u_s[r] = 0.0
        st = flow_into(rhs, xi, u_s, p, T, opts, K_s, ytmp, xi_out)
        if theta == 0:  # OVERFLOW received: zoom out from at least a small rescue radius, so
            # that a range that underflowed to 0 (long runs at small T) can still grow again
            rescue = 0.0
            for i in range(xi.shape[0]):
                rescue = max(rescue, abs(xi[i]))
            rescue = 1e-9 * (1.0 + rescue)
            En = sigma * Lambda * max(E, rescue)
        else:
            En = Lambda * E
    if En < E_min:
        En = E_min
    return En, st


# ----------------------------------------------------------------------------- codebook
@dataclass(frozen=True)
class Codebook:
    """Symbols, their bit width and byte packing for n coordinates and M levels."""

    n: int
    M: int
    resilient: bool = True

    def __post_init__(self):
        if self.n < 1 or self.M < 1:
            raise ValueError(f"codebook needs n >= 1 and M >= 1, got n={self.n}, M={self.M}")

    @property
    def n_boxes(self) -> int:
        return self.M**self.n

    @property
    def overflow(self) -> int:
        """The spare OVERFLOW codeword (resilient mode), or -1."""
        return self.n_boxes if self.resilient else -1

    @property
    def n_codes(self) -> int:
        return self.n_boxes + (1 if self.resilient else 0)

    @property
    def bits(self) -> int:
        """Bits per symbol: ceil(n log2 M) (ideal) or ceil(log2(M^n + 1)) (resilient)."""
        return max(1, (self.n_codes - 1).bit_length())

    @property
    def nbytes(self) -> int:
        return (self.bits + 7) // 8

    def pack(self, i: int) -> bytes:
        i = int(i)
        if not 0 <= i < self.n_codes:
            raise InvalidSymbol(f"symbol {i} outside the codebook 0..{self.n_codes - 1}")
        return i.to_bytes(self.nbytes, "big")

    def unpack(self, data: bytes) -> int:
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise InvalidSymbol(f"payload must be bytes, got {type(data).__name__}")
        data = bytes(data)
        if len(data) != self.nbytes:
            raise InvalidSymbol(f"payload of {len(data)} bytes, expected {self.nbytes}")
        i = int.from_bytes(data, "big")
        if i >= self.n_codes:
            raise InvalidSymbol(f"code {i} outside the codebook 0..{self.n_codes - 1}")
        return i


# ----------------------------------------------------------------------------- end points
@dataclass(frozen=True)
class QuantizerParams:
    """Everything both ends must share (the 'protocol')."""

    T: float
    M: int
    L: float
    E0: float
    mode: str = "resilient"
    zoom_out: float | None = None  # sigma; None -> M
    E_min: float = 0.0

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"quantizer mode must be one of {sorted(MODES)}, got {self.mode!r}")

    @property
    def Lambda(self) -> float:
        """Lambda = e^{L T} (Assumption 2 requires M > Lambda)."""
        return math.exp(self.L * self.T)

    @property
    def sigma(self) -> float:
        return float(self.M if self.zoom_out is None else self.zoom_out)

    @property
    def mode_code(self) -> int:
        return MODES[self.mode]


class _End:
    """State shared by the encoder and the decoder: xi_k, E_k and the sample index k."""

    def __init__(self, plant, K, qp: QuantizerParams, flow: FlowOptions = DEFAULT_FLOW):
        self.plant = plant
        self.K = np.ascontiguousarray(np.asarray(K, dtype=np.float64).reshape(plant.m, plant.n))
        self.qp = qp
        self.codebook = Codebook(plant.n, qp.M, resilient=(qp.mode == "resilient"))
        self._rhs = type(plant).rhs.cfunc
        self._p = plant.p
        self._opts = flow.as_array()
        self._Ks = np.empty((13, plant.n))
        self._ytmp = np.empty(plant.n)
        self._us = np.empty(plant.m)
        self.k = 0
        self.xi = np.zeros(plant.n)  # xi_0 = 0
        self.E = float(qp.E0)
        self.flow_status = 0

    def _update(self, theta: int, overflow: bool, q: np.ndarray) -> None:
        xi_next = np.empty(self.plant.n)
        qp = self.qp
        E_next, st = zoom_update(self._rhs, self._p, qp.T, self._opts, self.K, int(theta), bool(overflow),
                                 self.xi, self.E, q, qp.Lambda, qp.M, qp.sigma, qp.E_min,
                                 self._Ks, self._ytmp, self._us, xi_next)
        self.xi = xi_next
        self.E = float(E_next)
        self.flow_status = int(st)
        self.k += 1


class Encoder(_End):
    """Algorithm 1. ``encode(x_k)`` -> symbol; ``ack(theta_k)`` applies (xi), (E)."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.saturations = 0
        self._last: tuple[int, bool, np.ndarray] | None = None

    def encode(self, x) -> tuple[int, bool]:
        """Symbol for x_k and whether x_k was outside Q(xi_k, E_k) (a saturation event)."""
        x = np.asarray(x, dtype=np.float64)
        i, sat = quantize_index(x, self.xi, self.E, self.qp.M)
        if sat:
            self.saturations += 1
        q = np.empty(self.plant.n)
        box_center(i, self.xi, self.E, self.qp.M, q)
        if sat and self.codebook.resilient:
            i = self.codebook.overflow
        self._last = (int(i), bool(sat), q)
        return int(i), bool(sat)

    @property
    def q(self) -> np.ndarray:
        """q_k as the decoder will reconstruct it (when the packet arrives)."""
        return self._last[2]

    def ack(self, theta: int) -> None:
        if self._last is None:
            raise RuntimeError("ack() before encode()")
        i, _sat, q = self._last
        overflow = i == self.codebook.overflow
        self._update(int(theta), overflow, q)
        self._last = None


class Decoder(_End):
    """Algorithm 2 and the controller: ``step(symbol | None)`` -> (u_k, q_k, theta_k)."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.overflows = 0
        self.invalid = 0

    def step(self, symbol: int | None):
        """Decode the symbol received at t_k (None: lost), return (u_k, q_k, theta_k).

        An out-of-range symbol is counted in ``invalid`` and treated as a loss
        (theta_k = 1), which the ack tells the encoder, so both stay in lockstep.
        """
        n = self.plant.n
        cb = self.codebook
        overflow = False
        if symbol is not None and not (0 <= int(symbol) < cb.n_codes):
            self.invalid += 1
            symbol = None
        if symbol is None:
            theta = 1
            q = np.zeros(n)
        else:
            theta = 0
            if int(symbol) == cb.overflow:
                overflow = True
                self.overflows += 1
                q = np.zeros(n)
            else:
                q = np.empty(n)
                box_center(int(symbol), self.xi, self.E, self.qp.M, q)
        u = np.empty(self.plant.m)
        control_input(self.K, q, theta, overflow, u)
        self._update(theta, overflow, q)
        return u, q, theta
