"""The loop's parameter types and the codebook, without numba.

What a process needs to read and check a scenario, and what the attacker and the
launcher need of the quantizer, apart from the compiled kernels (``testbed.loop.flow``,
``testbed.loop.quantizer``, which re-export every name here): a process that only reads a
scenario never imports numba.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# ============================================================================ the flow map's options
FLOW_OK = 0
FLOW_DIVERGED = 1
FLOW_STEP_LIMIT = 2

STATUS_NAMES = {FLOW_OK: "ok", FLOW_DIVERGED: "diverged", FLOW_STEP_LIMIT: "step_limit"}


@dataclass(frozen=True)
class FlowOptions:
    """Tolerances of the flow map.

    rtol, atol : local error tolerances of the adaptive integrator.
    x_max      : a state with ||x||_inf above this is reported as diverged.
    max_steps  : step budget for one call of phi_T.
    """

    rtol: float = 1e-11
    atol: float = 1e-13
    x_max: float = 1e8
    max_steps: int = 20000

    def as_array(self) -> np.ndarray:
        return np.array([self.rtol, self.atol, self.x_max, float(self.max_steps)], dtype=np.float64)


DEFAULT_FLOW = FlowOptions()


# ============================================================================ the quantizer
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


class SymbolPacking:
    """A symbol 0 .. n_codes - 1 on the wire: big-endian in ``nbytes`` bytes; anything else is an
    :class:`InvalidSymbol` (the paper's codebook and a method's plain integer codes alike)."""

    n_codes: int
    nbytes: int

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


class CodebookTooLarge(ValueError):
    """A codebook beyond ``MAX_CODES`` (the scenario loader turns it into a ScenarioError)."""


# ----------------------------------------------------------------------------- codebook
@dataclass(frozen=True)
class Codebook(SymbolPacking):
    """Symbols, their bit width and byte packing for n coordinates and M levels."""

    n: int
    M: int
    resilient: bool = True

    def __post_init__(self) -> None:
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
    def n_codes(self) -> int:  # type: ignore[override]  # derived here, an attribute of IntCodebook
        return self.n_boxes + (1 if self.resilient else 0)

    @property
    def bits(self) -> int:
        """Bits per symbol: ceil(n log2 M) (ideal) or ceil(log2(M^n + 1)) (resilient)."""
        return max(1, (self.n_codes - 1).bit_length())

    @property
    def nbytes(self) -> int:  # type: ignore[override]
        return (self.bits + 7) // 8


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

    def __post_init__(self) -> None:
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


def corrupt_payload(codebook: Codebook, payload: bytes, kind: str) -> bytes:
    """The attacker's fault injection: an out-of-range code, or one byte too many."""
    if kind == "range" and codebook.n_codes < 256 ** codebook.nbytes:
        return (256 ** codebook.nbytes - 1).to_bytes(codebook.nbytes, "big")
    return payload + b"\xff"
