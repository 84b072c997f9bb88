"""The method interface: a coding-and-control method's encoder end and decoder end.

A *method* (public API, as stable as ``plants.Plant``) says how x_k becomes a symbol of a
declared number of bits at the encoder, and how the decoder turns a symbol, or a loss,
into the input u_k.  Both ends are pure, deterministic state machines: no clock, no
network, no randomness.  The protocol core (``testbed.loop.protocol``: acks, withholding, loss
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

What an end holds and may call (the model, K, the ``[quantizer]`` parameters, k, u_{k-1}, the
flow map ``phi_T``): :class:`End`.  Every bundled method, the paper's included
(``testbed.methods.paper``), is written against this interface and nothing else.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from ..common import validate
from ..loop.params import DEFAULT_FLOW, ROUNDOFF, Codebook, FlowOptions, InvalidSymbol, QuantizerParams, SymbolPacking

if TYPE_CHECKING:
    from plants.base import Plant

# a symbol: a code number (an int in 0 .. 2**bits - 1), the bytes of an unquantized state, or None (lost)
Symbol = Any


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

    def pack(self, s: object) -> bytes:
        if not isinstance(s, (bytes, bytearray)) or len(s) != self.nbytes:
            raise InvalidSymbol(f"symbol must be {self.nbytes} bytes")
        return bytes(s)

    def unpack(self, data: object) -> bytes:
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise InvalidSymbol(f"payload must be bytes, got {type(data).__name__}")
        data = bytes(data)
        if len(data) != self.nbytes:
            raise InvalidSymbol(f"payload of {len(data)} bytes, expected {self.nbytes}")
        return data

    @staticmethod
    def encode_state(x: np.ndarray) -> bytes:
        return np.asarray(x, dtype=">f8").tobytes()

    @staticmethod
    def decode_state(s: bytes) -> np.ndarray:
        return np.frombuffer(s, dtype=">f8").astype(np.float64)


def symbol_code(symbol: Symbol) -> int:
    """The integer a record keeps for a symbol (-1: none; 0 for a symbol that is not a code
    number, such as the exact state of an unquantized method)."""
    if symbol is None:
        return -1
    if isinstance(symbol, (bytes, bytearray)):
        return 0
    return int(symbol)


def valid_symbol(codebook: SymbolPacking | FloatCodebook, symbol: Symbol) -> bool:
    """Whether ``symbol`` is a code of ``codebook`` (an out-of-range code is treated as a loss)."""
    if isinstance(codebook, FloatCodebook):
        return isinstance(symbol, (bytes, bytearray)) and len(symbol) == codebook.nbytes
    try:
        return 0 <= int(symbol) < codebook.n_codes
    except (TypeError, ValueError):
        return False


class End:
    """What an end holds and may call (both ends; the end API of docs/methods.md).

    Built by :meth:`Method.make_encoder` / :meth:`Method.make_decoder` as ``End(method, model, K, qp,
    flow)``, the one constructor of every end (a subclass that sets its own start state calls
    ``super().__init__(*a, **kw)`` first).  It holds:

    * ``method``: the :class:`Method` instance, its ``[method] params`` in ``method.params``;
    * ``plant``: the model the method predicts with (``[model]``, else the plant: ``plants.Plant``,
      with ``n``, ``m``, ``f(x, u)``, ``A``, ``B``), never the true plant;
    * ``K``: the gain of control law (2), an (m, n) float64 array;
    * ``qp``: the scenario's ``[quantizer]`` (``loopspec.QuantizerParams``): ``T`` the period, ``M``,
      ``L``, ``E0``, ``Lambda`` = e^{L T}, ``sigma`` (zoom-out), ``E_min``, ``mode``, ``rule``;
    * ``flow``: the flow map's options (tolerances, ``x_max``);
    * ``codebook``: ``method.codebook(n, qp)``;
    * ``k``: the sample index (0 at the start; the testbed adds 1 after every ``update``);
    * ``xi``, ``E``: the range's centre and radius (zeros and 0.0 at the start: an end that starts
      elsewhere, the paper's at E0, sets them in ``__init__``); with ``state()``, what the lockstep
      check compares;
    * ``u_prev``: u_{k-1}, the input both ends know was applied (zeros at the start; an end that
      uses it keeps it current in ``update``, as the paper's ends do);
    * ``flow_status``: the status of the last :meth:`phi_T` (0: ok).

    and offers the paper's own arithmetic, so that a method configured like the paper's computes its
    numbers bit for bit: :meth:`phi_T` (the model's flow map over T), :meth:`feedback` (u = K q) and
    :meth:`floor_E` (the floor of rule (E)).
    """

    def __init__(self, method: Method, model: Plant, K: np.ndarray, qp: QuantizerParams,
                 flow: FlowOptions = DEFAULT_FLOW):
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
        self._phi: Callable[..., int] | None = None

    def state(self) -> np.ndarray:
        """The state both ends must share (lockstep), checked by the testbed: xi_k and E_k by default."""
        return np.concatenate([self.xi, [self.E]])

    def phi_T(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """phi_T(x, u): the model's state one period T after x under the held input u (a new array).

        The flow map of ``testbed.loop.flow`` (``flow_into``, adaptive Dormand-Prince 8(5,3)) with the
        model's right-hand side and the scenario's ``[flow]`` options: the function the paper's rule
        (xi) calls, xi_{k+1} = phi_T(q_k, K q_k) or phi_T(xi_k, 0).  Always finite; the status
        (0 ok, 1 diverged past ``x_max``, 2 step limit) is left in ``flow_status``.
        """
        from ..loop.flow import compiled_for, flow_into  # compiled: loaded when a run starts

        n, m = self.plant.n, self.plant.m
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(n)
        u = np.ascontiguousarray(u, dtype=np.float64).reshape(m)
        out = np.empty(n)
        if self._phi is None:
            self._phi_const = (type(self.plant).rhs.cfunc, self.plant.p, self.flow.as_array(),
                               np.empty((13, n)), np.empty(n))
        rhs, p, opts, Ks, ytmp = self._phi_const
        args = (rhs, x, u, p, float(self.qp.T), opts, Ks, ytmp, out)
        if self._phi is None:
            st = flow_into(*args)
            self._phi = compiled_for(flow_into, args)  # a live node calls it every sample: no type dispatch
        else:
            st = self._phi(*args)
        self.flow_status = int(st)
        return out

    def feedback(self, q: np.ndarray) -> np.ndarray:
        """u = K q, the state feedback of control law (2), summed in the order the paper's ends sum it."""
        q = np.asarray(q, dtype=np.float64).reshape(self.plant.n)
        u = np.empty(self.plant.m)
        for r in range(self.plant.m):
            acc = 0.0
            for j in range(self.plant.n):
                acc += float(self.K[r, j]) * float(q[j])
            u[r] = acc
        return u

    def floor_E(self, E: float, xi_next: np.ndarray) -> float:
        """E_{k+1} as rule (E) of the paper's ends floors it: never below the round-off of the box
        arithmetic around xi_{k+1} (``ROUNDOFF`` ||xi_{k+1}||_inf, 16 ulp), nor below ``qp.E_min``."""
        big = 0.0
        for v in np.asarray(xi_next, dtype=np.float64).ravel():
            big = max(big, abs(float(v)))
        E = float(E)
        if E < ROUNDOFF * big:
            E = ROUNDOFF * big
        if E < self.qp.E_min:
            E = float(self.qp.E_min)
        return E


class EncoderEnd(End):
    """The encoder end of a method (Algorithm 1's place).  Override ``symbol`` and ``update``.

    The testbed calls ``encode(x_k)`` (which calls ``symbol``), then, once theta_k is known,
    ``ack(theta_k)`` (which calls ``update`` and advances ``k``).  Besides :class:`End`'s members:
    ``q`` (q_k of this sample, readable in ``update``) and ``saturations`` (counted from ``symbol``).
    """

    def __init__(self, *a: Any, **kw: Any):
        super().__init__(*a, **kw)
        self.saturations = 0
        self._last: tuple[Symbol, np.ndarray] | None = None

    def symbol(self, x: np.ndarray) -> tuple[Symbol, bool, np.ndarray]:
        """(symbol, saturated, q_k) for x_k."""
        raise NotImplementedError

    def update(self, theta: int, symbol: Symbol) -> None:
        """theta_k is known (1: lost): update the encoder's state for sample k + 1."""

    # --- what the protocol calls
    def encode(self, x: np.ndarray) -> tuple[Symbol, bool]:
        """The symbol for x_k and whether x_k was outside the range (``symbol``; a saturation is counted)."""
        x = np.asarray(x, dtype=np.float64)
        s, sat, q = self.symbol(x)
        if sat:
            self.saturations += 1
        self._last = (s, np.asarray(q, dtype=np.float64))
        return s, bool(sat)

    @property
    def q(self) -> np.ndarray:
        """q_k as the decoder will reconstruct it (from ``encode`` until ``update`` returns)."""
        if self._last is None:
            raise RuntimeError("q read outside encode() .. update()")
        return self._last[1]

    def ack(self, theta: int) -> None:
        """theta_k of the sample ``encode`` sent: ``update(theta_k, symbol)``, then k + 1."""
        if self._last is None:
            raise RuntimeError("ack() before encode()")
        try:
            self.update(int(theta), self._last[0])
        finally:
            self._last = None
        self.k += 1


class DecoderEnd(End):
    """The decoder end (and the control law) of a method (Algorithm 2's place).  Override ``control``
    and ``update``.

    The testbed calls ``decide(symbol | None)`` (which calls ``control`` and returns u_k, q_k,
    theta_k), sends u_k, then ``commit()`` (which calls ``update`` and advances ``k``); ``step`` is
    the two at once.  A symbol outside the codebook is counted in ``invalid`` and is a loss.
    Besides :class:`End`'s members: ``invalid`` and ``overflows`` (an end with an OVERFLOW code
    counts the ones it received).
    """

    def __init__(self, *a: Any, **kw: Any):
        super().__init__(*a, **kw)
        self.overflows = 0
        self.invalid = 0
        self._pending: tuple[int, Symbol] | None = None

    def control(self, symbol: Symbol) -> tuple[np.ndarray, np.ndarray]:
        """(u_k, q_k) for a received symbol, or for a loss (``symbol is None``)."""
        raise NotImplementedError

    def update(self, theta: int, symbol: Symbol) -> None:
        """After sample k (theta_k known): the decoder's state for sample k + 1."""

    # --- what the protocol calls
    def decide(self, symbol: Symbol) -> tuple[np.ndarray, np.ndarray, int]:
        """(u_k, q_k, theta_k) for the symbol received at t_k (None: lost), without ``update``.

        A live controller sends u_k between ``decide`` and ``commit``: the decoder's update (a
        prediction phi_T) is not on the path of u_k.  ``decide`` again before ``commit`` is an error.
        """
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
        """``update(theta_k, symbol)`` of the sample ``decide`` decided, then k + 1."""
        if self._pending is None:
            raise RuntimeError("Decoder.commit() without decide()")
        theta, symbol = self._pending
        self._pending = None
        self.update(theta, symbol)
        self.k += 1

    def step(self, symbol: Symbol) -> tuple[np.ndarray, np.ndarray, int]:
        """``decide`` then ``commit``: (u_k, q_k, theta_k)."""
        out = self.decide(symbol)
        self.commit()
        return out


class Method:
    """A coding-and-control method: parameters and a factory of its two ends.

    Class attributes: ``name``, ``description`` (one line), ``uses`` (the ``[quantizer]`` keys
    besides T it reads), ``defaults`` (its ``[method] params`` and their default values),
    ``encoder_class`` and ``decoder_class`` (its :class:`EncoderEnd` and :class:`DecoderEnd`
    subclasses), ``kernel_mode`` (the batch kernel's code for a bundled method; None: the
    per-sample simulator and the live nodes only), ``source`` (the paper it comes from).
    """

    name: str = ""
    description: str = ""
    source: str = ""
    uses: tuple[str, ...] = ()
    defaults: ClassVar[dict[str, Any]] = {}
    kernel_mode: int | None = None
    encoder_class: type[EncoderEnd] | None = None
    decoder_class: type[DecoderEnd] | None = None

    def __init__(self, **params: Any):
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

    def bits(self, n: int, qp: QuantizerParams) -> int:
        """Bits per sample for a state of n coordinates (``qp``: the scenario's ``[quantizer]``)."""
        return int(self.codebook(n, qp).bits)

    def codebook(self, n: int, qp: QuantizerParams) -> Any:
        """The codebook (``pack``, ``unpack``, ``bits``, ``nbytes``, ``n_codes``, ``overflow``)."""
        raise NotImplementedError

    def make_encoder(self, model: Plant, K: np.ndarray, qp: QuantizerParams,
                     flow: FlowOptions = DEFAULT_FLOW) -> EncoderEnd:
        """The encoder end: ``encoder_class(self, model, K, qp, flow)``."""
        if self.encoder_class is None:
            raise MethodError(f"method {self.display_name()!r} has no encoder_class")
        return self.encoder_class(self, model, K, qp, flow)

    def make_decoder(self, model: Plant, K: np.ndarray, qp: QuantizerParams,
                     flow: FlowOptions = DEFAULT_FLOW) -> DecoderEnd:
        """The decoder end: ``decoder_class(self, model, K, qp, flow)``."""
        if self.decoder_class is None:
            raise MethodError(f"method {self.display_name()!r} has no decoder_class")
        return self.decoder_class(self, model, K, qp, flow)

    def kernel_code(self, qp: QuantizerParams) -> int | None:
        """The batch kernel's mode for this method under ``qp`` (None: no kernel)."""
        return self.kernel_mode

    def kernel_E0(self, qp: QuantizerParams) -> float:
        """The E0 the batch kernel starts from (the method's own range where it has one)."""
        return float(qp.E0)


@dataclass(frozen=True)
class MethodQuantizerParams(QuantizerParams):
    """A loop's ``QuantizerParams`` carrying its method, for the batch kernel (``simulate_batch``) of the
    analyses (sweep, roa --vulnerable, worst-attack, vulnerability), which pass the quantizer around."""

    method: object = field(default=None, compare=False, repr=False)


def finite_params(method: Method, *names: str) -> None:
    for k in names:
        try:
            validate.positive(method.params[k])
        except validate.Invalid as e:
            raise MethodError(f"method {method.display_name()!r}: parameter {k} {e}") from None


__all__ = ["Method", "End", "EncoderEnd", "DecoderEnd", "MethodError", "IntCodebook", "FloatCodebook", "Codebook",
           "symbol_code", "valid_symbol"]
