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

from .flow import DEFAULT_FLOW, FlowOptions, compiled_for, flow_into

MODE_IDEAL = 0
MODE_RESILIENT = 1
MODE_NONE = 2  # no quantization at all (q_k = x_k): the nominal loop of the region of attraction
MODES = {"ideal": MODE_IDEAL, "resilient": MODE_RESILIENT, "none": MODE_NONE}
RULES = ("paper", "delay-aware")

#: E_{k+1} >= ROUNDOFF ||xi_{k+1}||_inf: 16 ulp, the round-off of the box arithmetic and the flow map
ROUNDOFF = 16 * 2.0 ** -52

#: the largest codebook the testbed carries end to end: a symbol is a 32-bit field of the
#: telemetry and the recording (and an int64 in the batch kernel's arithmetic)
MAX_CODES = 2**31 - 1


def delay_margin_gain(Lambda: float, L_u: float, nominal: float, lo: float, hi: float) -> float:
    """The delay-aware rule's margin per unit input change: Lambda L_u w, w = max(nominal - lo, hi - nominal).

    If the plant switches from u_{k-1} to u_k at delta in [lo, hi] instead of the predicted
    delta_hat = ``nominal``, the two trajectories from one initial point differ only while
    their inputs differ, for |delta - delta_hat| <= w seconds, where
    ||f(x, u_{k-1}) - f(x, u_k)||_inf <= L_u ||u_{k-1} - u_k||_inf; Gronwall's inequality with
    the Lipschitz constant L gives a gap of at most e^{L T} L_u w ||u_k - u_{k-1}||_inf at
    t_{k+1} (docs/paper.md, "The delay-aware rule").
    """
    w = max(nominal - lo, hi - nominal, 0.0)
    return float(Lambda * L_u * w)


class InvalidSymbol(ValueError):
    """A payload that is not a code of the codebook (wrong length or out of range)."""


class CodebookTooLarge(ValueError):
    """A codebook beyond ``MAX_CODES`` (the scenario loader turns it into a ScenarioError)."""


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
def zoom_update(rhs, p, T, opts, Kgain, theta, overflow, xi, E, q, u_prev, Lambda, M, sigma,
                E_min, dpar, K_s, ytmp, u_s, xi_out):
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
    # never below the round-off of the box arithmetic around xi_{k+1} (a few ulp): a range
    # narrower than that cannot hold x_{k+1} however exact the prediction
    big = 0.0
    for i in range(xi_out.shape[0]):
        big = max(big, abs(xi_out[i]))
    if En < ROUNDOFF * big:
        En = ROUNDOFF * big
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
        if self.n_codes > MAX_CODES:
            raise CodebookTooLarge(f"M^n = {self.M}^{self.n} codes{' + OVERFLOW' if self.resilient else ''} exceed "
                                   f"the limit of 2^31 - 1 codes per symbol (31 bits): lower M or n")

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
    rule: str = "paper"            # prediction rule: "paper" | "delay-aware"
    delay_hat: float = 0.0         # delay-aware rule: nominal actuation delay [s] of a received sample
    margin_gain: float = 0.0       # ... and its margin: E_{k+1} += margin_gain ||u_k - u_{k-1}||_inf
    delay_hat_lost: float = 0.0    # the same for a sample decided lost (u_k = 0 sent at the loss deadline)
    margin_gain_lost: float = 0.0

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"quantizer mode must be one of {sorted(MODES)}, got {self.mode!r}")
        if self.rule not in RULES:
            raise ValueError(f"quantizer rule must be one of {RULES}, got {self.rule!r}")

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

    @property
    def dpar(self) -> np.ndarray:
        """The delay-aware rule's parameters as ``zoom_update`` takes them."""
        return np.array([self.delay_hat, self.margin_gain, self.delay_hat_lost, self.margin_gain_lost])


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
        self._dpar = qp.dpar
        self._ytmp = np.empty(plant.n)
        self.k = 0
        self.xi = np.zeros(plant.n)  # xi_0 = 0
        self.E = float(qp.E0)
        self.u_prev = np.zeros(plant.m)  # u_{k-1} as both ends know it (u_{-1} = 0)
        self.flow_status = 0
        self._zoom = None

    def _update(self, theta: int, overflow: bool, q: np.ndarray) -> None:
        xi_next = np.empty(self.plant.n)
        u_k = np.empty(self.plant.m)
        qp = self.qp
        args = (self._rhs, self._p, qp.T, self._opts, self.K, int(theta), bool(overflow),
                self.xi, float(self.E), q, self.u_prev, qp.Lambda, qp.M, qp.sigma, qp.E_min,
                self._dpar, self._Ks, self._ytmp, u_k, xi_next)
        if self._zoom is None:
            E_next, st = zoom_update(*args)
            self._zoom = compiled_for(zoom_update, args)  # once per sample on a live node: no type dispatch
        else:
            E_next, st = self._zoom(*args)
        self.xi = xi_next
        self.E = float(E_next)
        self.u_prev = u_k
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
        self._pending: tuple[int, bool, np.ndarray] | None = None

    def step(self, symbol: int | None):
        """Decode the symbol received at t_k (None: lost), return (u_k, q_k, theta_k).

        An out-of-range symbol is counted in ``invalid`` and treated as a loss
        (theta_k = 1), which the ack tells the encoder, so both stay in lockstep.
        ``decide`` then ``commit``: the same in two steps.
        """
        out = self.decide(symbol)
        self.commit()
        return out

    def decide(self, symbol: int | None):
        """(u_k, q_k, theta_k) of Algorithm 2 and law (2), without the update (xi), (E) of ``commit``.

        A live controller sends u_k between the two: the prediction xi_k+1 = phi_T(q_k, u_k)
        is not on the path of u_k.  ``decide`` again before ``commit`` is an error.
        """
        if self._pending is not None:
            raise RuntimeError("Decoder.decide() twice without commit()")
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
        self._pending = (theta, overflow, q)
        return u, q, theta

    def commit(self) -> None:
        """Apply (xi), (E) for the sample ``decide`` decided: xi_k+1, E_k+1 (Algorithm 2)."""
        if self._pending is None:
            raise RuntimeError("Decoder.commit() without decide()")
        theta, overflow, q = self._pending
        self._pending = None
        self._update(theta, overflow, q)
