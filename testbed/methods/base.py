"""The method interface: a coding-and-control method's encoder end and decoder end.

A *method* (public API, as stable as ``plants.Plant``) says how x_k becomes a symbol of a
declared number of bits at the encoder, and how the decoder turns a symbol, or a loss,
into the input u_k.  Both ends are pure, deterministic state machines: no clock, no
network, no randomness.  The protocol core (``testbed.protocol``: acks, withholding, loss
deadlines) runs them, in the per-sample simulator and in the live nodes alike, so every
method gets the same ack protocol, faults, recording and re-simulation.

Writing a method: subclass :class:`Method` and give it an encoder end and a decoder end
(subclasses of :class:`EncoderEnd` and :class:`DecoderEnd`):

* ``EncoderEnd.symbol(x)`` -> ``(symbol, saturated, q)``: the code for x_k (an int in
  ``0 .. 2**bits - 1``), whether x_k was outside the range the method covers, and q_k as the
  decoder will reconstruct it (for the record).  ``EncoderEnd.update(theta, symbol)``: what
  the encoder does when it learns theta_k (1: the packet was lost).
* ``DecoderEnd.control(symbol)`` -> ``(u, q)``: u_k and q_k for a received symbol, or for a
  loss (``symbol is None``, the input applied through the loss).  ``DecoderEnd.update(theta,
  symbol)``: the decoder's update after sample k (it knows theta_k too).

The two ends must stay in *lockstep*: their shared state (``state()``, by default xi_k and
E_k) must be equal at every sample.  The testbed checks it at every sample the encoder sent
and reports a method that breaks it.  ``[quantizer] T`` is every method's period; a method
lists the other ``[quantizer]`` keys it uses in ``uses`` and its own parameters (the
scenario's ``[method] params``) with their defaults in ``defaults``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..loopspec import Codebook, InvalidSymbol, QuantizerParams, SymbolPacking


class MethodError(ValueError):
    """A method that cannot be used (a bad reference, parameter or key), with the reason (one line)."""


class IntCodebook(SymbolPacking):
    """Symbols 0 .. 2^bits - 1 packed big-endian into ceil(bits / 8) bytes (a user method's default)."""

    resilient = False
    overflow = -1

    def __init__(self, bits: int):
        self.bits = int(bits)
        if not 1 <= self.bits <= 31:
            raise MethodError(f"a method's symbol has 1..31 bits, got {bits}")
        self.n_codes = 1 << self.bits
        self.nbytes = (self.bits + 7) // 8


class FloatCodebook:
    """The exact state: n IEEE-754 doubles (64 n bits), the symbol is their bytes (big-endian)."""

    resilient = False
    overflow = -1

    def __init__(self, n: int):
        self.n = int(n)
        self.bits = 64 * self.n
        self.nbytes = 8 * self.n
        self.n_codes = 256 ** self.nbytes   # every payload of the right length is a code

    def pack(self, s) -> bytes:
        if not isinstance(s, (bytes, bytearray)) or len(s) != self.nbytes:
            raise InvalidSymbol(f"symbol must be {self.nbytes} bytes")
        return bytes(s)

    def unpack(self, data) -> bytes:
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise InvalidSymbol(f"payload must be bytes, got {type(data).__name__}")
        data = bytes(data)
        if len(data) != self.nbytes:
            raise InvalidSymbol(f"payload of {len(data)} bytes, expected {self.nbytes}")
        return data

    @staticmethod
    def encode_state(x) -> bytes:
        return np.asarray(x, dtype=">f8").tobytes()

    @staticmethod
    def decode_state(s) -> np.ndarray:
        return np.frombuffer(s, dtype=">f8").astype(np.float64)


def symbol_code(symbol) -> int:
    """The integer a record keeps for a symbol (-1: none; 0 for a symbol that is not a code
    number, such as the exact state of an unquantized method)."""
    if symbol is None:
        return -1
    if isinstance(symbol, (bytes, bytearray)):
        return 0
    return int(symbol)


def valid_symbol(codebook, symbol) -> bool:
    """Whether ``symbol`` is a code of ``codebook`` (an out-of-range code is treated as a loss)."""
    if isinstance(codebook, FloatCodebook):
        return isinstance(symbol, (bytes, bytearray)) and len(symbol) == codebook.nbytes
    try:
        return 0 <= int(symbol) < codebook.n_codes
    except (TypeError, ValueError):
        return False


class _EndBase:
    def __init__(self, method: "Method", model, K, qp, flow):
        self.method = method
        self.plant = model
        self.K = np.ascontiguousarray(np.asarray(K, dtype=np.float64).reshape(model.m, model.n))
        self.qp = qp
        self.flow = flow
        self.codebook = method.codebook(model.n, qp)
        self.k = 0
        self.xi = np.zeros(model.n)
        self.E = 0.0
        self.u_prev = np.zeros(model.m)
        self.flow_status = 0

    def state(self) -> np.ndarray:
        """The state both ends must share (lockstep), checked by the testbed: xi_k and E_k by default."""
        return np.concatenate([self.xi, [self.E]])


class EncoderEnd(_EndBase):
    """The encoder end of a method.  Override ``symbol`` and ``update``."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.saturations = 0
        self._last = None

    def symbol(self, x: np.ndarray):
        """(symbol, saturated, q_k) for x_k."""
        raise NotImplementedError

    def update(self, theta: int, symbol) -> None:
        """theta_k is known (1: lost): update the encoder's state for sample k + 1."""

    # --- what the protocol calls
    def encode(self, x):
        x = np.asarray(x, dtype=np.float64)
        s, sat, q = self.symbol(x)
        if sat:
            self.saturations += 1
        self._last = (s, np.asarray(q, dtype=np.float64))
        return s, bool(sat)

    @property
    def q(self) -> np.ndarray:
        return self._last[1]

    def ack(self, theta: int) -> None:
        if self._last is None:
            raise RuntimeError("ack() before encode()")
        s, _q = self._last
        self._last = None
        self.update(int(theta), s)
        self.k += 1


class DecoderEnd(_EndBase):
    """The decoder end (and the control law) of a method.  Override ``control`` and ``update``."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.overflows = 0
        self.invalid = 0
        self._pending = None

    def control(self, symbol):
        """(u_k, q_k) for a received symbol, or for a loss (``symbol is None``)."""
        raise NotImplementedError

    def update(self, theta: int, symbol) -> None:
        """After sample k (theta_k known): the decoder's state for sample k + 1."""

    # --- what the protocol calls
    def decide(self, symbol):
        if self._pending is not None:
            raise RuntimeError("Decoder.decide() twice without commit()")
        if symbol is not None and not valid_symbol(self.codebook, symbol):
            self.invalid += 1
            symbol = None
        theta = 1 if symbol is None else 0
        u, q = self.control(symbol)
        u = np.asarray(u, dtype=np.float64).reshape(self.plant.m)
        q = np.asarray(q, dtype=np.float64).reshape(self.plant.n)
        self._pending = (theta, symbol)
        return u, q, theta

    def commit(self) -> None:
        if self._pending is None:
            raise RuntimeError("Decoder.commit() without decide()")
        theta, symbol = self._pending
        self._pending = None
        self.update(theta, symbol)
        self.k += 1

    def step(self, symbol):
        out = self.decide(symbol)
        self.commit()
        return out


class Method:
    """A coding-and-control method: parameters and a factory of its two ends.

    Class attributes: ``name``, ``description`` (one line), ``uses`` (the ``[quantizer]`` keys
    besides T it reads), ``defaults`` (its ``[method] params`` and their default values),
    ``kernel_mode`` (the batch kernel's code for a bundled method; None: the per-sample
    simulator and the live nodes only), ``source`` (the paper it comes from).
    """

    name: str = ""
    description: str = ""
    source: str = ""
    uses: tuple[str, ...] = ()
    defaults: dict = {}
    kernel_mode: int | None = None
    encoder_class: type | None = None
    decoder_class: type | None = None

    def __init__(self, **params):
        unknown = sorted(set(params) - set(self.defaults))
        if unknown:
            allowed = ", ".join(sorted(self.defaults)) or "none"
            raise MethodError(f"method {self.display_name()!r} has no parameter {unknown[0]!r} (parameters: {allowed})")
        self.params = {**self.defaults, **params}
        self.check_params()

    @classmethod
    def display_name(cls) -> str:
        return cls.name or cls.__name__

    def check_params(self) -> None:
        """Validate ``self.params`` (raise :class:`MethodError` with one line)."""

    def bits(self, n: int, qp) -> int:
        """Bits per sample for a state of n coordinates (``qp``: the scenario's ``[quantizer]``)."""
        return int(self.codebook(n, qp).bits)

    def codebook(self, n: int, qp):
        """The codebook (``pack``, ``unpack``, ``bits``, ``nbytes``, ``n_codes``, ``overflow``)."""
        raise NotImplementedError

    def make_encoder(self, model, K, qp, flow):
        return self.encoder_class(self, model, K, qp, flow)

    def make_decoder(self, model, K, qp, flow):
        return self.decoder_class(self, model, K, qp, flow)

    def kernel_code(self, qp) -> int | None:
        """The batch kernel's mode for this method under ``qp`` (None: no kernel)."""
        return self.kernel_mode

    def kernel_E0(self, qp) -> float:
        """The E0 the batch kernel starts from (the method's own range where it has one)."""
        return float(qp.E0)


@dataclass(frozen=True)
class MethodQuantizerParams(QuantizerParams):
    """A loop's ``QuantizerParams`` carrying its method, for the batch kernel (``simulate_batch``) of the
    analyses (sweep, roa --vulnerable, worst-attack, vulnerability), which pass the quantizer around."""

    method: object = field(default=None, compare=False, repr=False)


def finite_params(method: Method, *names: str) -> None:
    for k in names:
        v = method.params[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise MethodError(f"method {method.display_name()!r}: parameter {k} must be a positive number, got {v!r}")


__all__ = ["Method", "EncoderEnd", "DecoderEnd", "MethodError", "IntCodebook", "FloatCodebook", "Codebook",
           "symbol_code", "valid_symbol"]
