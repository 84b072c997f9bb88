"""Messages of a live run: small dataclasses with symmetric ``encode`` / ``decode``.

All times are integer nanoseconds since the run's start instant t0 (``Start.t0_ns``,
shared by every node; see ``testbed.nodes.clock.RunClock``), so t_k = k T_ns.

Control path (``loop/*`` keys).  The payload carries exactly the data of the paper;
the sample index and a time stamp travel beside it as a Zenoh attachment
(``Header``, ``HEADER_SIZE`` = 12 bytes: uint32 k, int64 stamp):

* ``Sensor``     payload n float64: x_k                           (plant -> encoder)
* ``Symbol``     payload the packed symbol bits, ``Codebook.pack`` (encoder -> controller),
                 1 byte for the paper's M = 6, n = 2
* ``Actuation``  payload uint8 theta_k + int32 last_rx + m float64 u_k  (controller -> plant, and
                 -> encoder: the ideal ack rides on it, ``last_rx`` as in ``Ack``)
* ``Ack``        payload uint8 theta_k + int32 last_rx             (controller -> encoder, when the
                 ack is a message of its own: ``--separate-ack``, or routed via the attacker)

Telemetry (``telemetry/<node>``: one little-endian binary record per sample,
records batched ``pack_batch`` / ``unpack_batch`` so that a message carries at
most ~20 ms of samples: one record per message at T = 0.1 s, 20 at T = 1 ms) and
the rare bookkeeping messages (``Start``, ``Stop``, ``Event``, ``AttackerStatus``,
``NodeSummary``: JSON) carry everything in the payload.

Every ``decode`` raises ``MessageError`` (a ``ValueError``) on a malformed input.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, ClassVar

__all__ = [
    "MessageError", "Header", "HEADER_SIZE", "WARMUP_K", "Sensor", "Symbol", "Actuation", "Ack",
    "PlantTelemetry", "EncoderTelemetry", "ControllerTelemetry", "AttackerTelemetry",
    "Start", "Stop", "Event", "AttackerStatus", "NodeSummary", "TELEMETRY_TYPES",
    "NO_TIME", "THETA_NONE", "pack_batch", "unpack_batch", "PROTOCOL_VERSION", "ProtocolMismatch",
    "STATE_NONFINITE", "STATE_WRONG_LENGTH", "state_fault",
]


class MessageError(ValueError):
    """A payload or attachment that is not a well-formed message."""


#: the wire protocol's version (docs/protocol.md, "Versioning"): carried by ``Start.protocol``, the one
#: message every node reads before the first sample; bumped whenever a key, a byte layout, a field of a
#: JSON message or a rule of the protocol changes in a way a node of the previous version would misread
PROTOCOL_VERSION = 1


class ProtocolMismatch(MessageError):
    """A ``Start`` of another protocol version (``theirs``; 0: a Start that carries none)."""

    def __init__(self, theirs):
        self.theirs = theirs
        super().__init__(f"the run speaks protocol version {repr(theirs)[:40]}, this node speaks {PROTOCOL_VERSION}")


NO_TIME = -(2**63)     # "never happened" for an int64 time stamp
THETA_NONE = 255       # theta unknown (u_k never arrived)
WARMUP_K = 0xFFFFFFFF  # header index of warm-up puts before t0: readers ignore it

_HEADER = struct.Struct("<Iq")
HEADER_SIZE = _HEADER.size


def _bytes(data: object) -> bytes:
    if data is None:
        raise MessageError("missing payload or attachment")
    if hasattr(data, "to_bytes"):  # zenoh.ZBytes
        data = data.to_bytes()
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise MessageError(f"expected bytes, got {type(data).__name__}")
    return bytes(data)


def _floats(data: bytes, what: str) -> tuple[float, ...]:
    if len(data) % 8:
        raise MessageError(f"{what}: {len(data)} bytes is not a whole number of float64")
    return struct.unpack(f"<{len(data) // 8}d", data)


@dataclass(frozen=True, slots=True)
class Header:
    """Attachment of every control-path message: sample index k and a time stamp (ns since t0)."""

    k: int
    stamp_ns: int

    def encode(self) -> bytes:
        return _HEADER.pack(self.k, self.stamp_ns)

    @classmethod
    def decode(cls, data: object) -> Header:
        data = _bytes(data)
        if len(data) != HEADER_SIZE:
            raise MessageError(f"header of {len(data)} bytes, expected {HEADER_SIZE}")
        return cls(*_HEADER.unpack(data))

    @property
    def warmup(self) -> bool:
        return self.k == WARMUP_K


# ============================================================================ control path
@dataclass(frozen=True, slots=True)
class Sensor:
    """x_k sampled by the plant at its sample instant ``stamp_ns`` (sent to the encoder)."""

    k: int
    stamp_ns: int
    x: tuple[float, ...]

    def encode(self) -> tuple[bytes, bytes]:
        return struct.pack(f"<{len(self.x)}d", *self.x), Header(self.k, self.stamp_ns).encode()

    @classmethod
    def decode(cls, payload: object, attachment: object) -> Sensor:
        h = Header.decode(attachment)
        x = _floats(_bytes(payload), "sensor")
        if not x:
            raise MessageError("sensor: empty state")
        return cls(h.k, h.stamp_ns, x)


#: the kinds of a wrong x_k from the plant (the encoder's events; the run's faults: ``testbed.live.devicefaults``)
STATE_NONFINITE, STATE_WRONG_LENGTH = "state_nonfinite", "state_wrong_length"


def state_fault(x: Sequence[float], n: int) -> tuple[str, str] | None:
    """What is wrong with an x_k the plant sent, as (kind, why), or None: its length is not the plant's n,
    or an entry is not finite (NaN, inf)."""
    if len(x) != n:
        return STATE_WRONG_LENGTH, f"x has {len(x)} entries, plant has n = {n}"
    if not all(math.isfinite(v) for v in x):
        return STATE_NONFINITE, f"x has a non-finite entry: {list(x)}"
    return None


@dataclass(frozen=True, slots=True)
class Symbol:
    """The encoder's symbol for sample k: ``data`` is exactly the packed code (``Codebook.pack``).

    Decoding checks only the header; the controller unpacks ``data`` with its
    codebook, which rejects a wrong length or an out-of-range code.
    """

    k: int
    stamp_ns: int
    data: bytes

    def encode(self) -> tuple[bytes, bytes]:
        return bytes(self.data), Header(self.k, self.stamp_ns).encode()

    @classmethod
    def decode(cls, payload: object, attachment: object) -> Symbol:
        h = Header.decode(attachment)
        return cls(h.k, h.stamp_ns, _bytes(payload))


_ACT = struct.Struct("<Bi")


@dataclass(frozen=True, slots=True)
class Actuation:
    """u_k = (1 - theta_k) K q_k for sample k (control law (2)), controller -> plant.

    It also carries the ack of sample k (Algorithms 1 and 2): theta_k and ``last_rx``,
    the latest sample whose symbol the decoder accepted (-1: none), as ``Ack`` does; with
    the paper's ideal ack the encoder reads them from this message (one put, two readers).
    """

    k: int
    stamp_ns: int
    theta: int
    u: tuple[float, ...]
    last_rx: int = -1

    def encode(self) -> tuple[bytes, bytes]:
        return (_ACT.pack(self.theta, self.last_rx) + struct.pack(f"<{len(self.u)}d", *self.u),
                Header(self.k, self.stamp_ns).encode())

    @classmethod
    def decode(cls, payload: object, attachment: object) -> Actuation:
        h = Header.decode(attachment)
        data = _bytes(payload)
        if len(data) < _ACT.size + 8:
            raise MessageError(f"actuation of {len(data)} bytes is too short")
        theta, last_rx = _ACT.unpack_from(data)
        if theta > 1:
            raise MessageError(f"actuation: theta = {theta} is not 0 or 1")
        return cls(h.k, h.stamp_ns, theta, _floats(data[_ACT.size:], "actuation"), last_rx)

    def ack(self) -> "Ack":
        """The ack this actuation carries."""
        return Ack(self.k, self.stamp_ns, self.theta, self.last_rx)


_ACK = struct.Struct("<Bi")


@dataclass(frozen=True, slots=True)
class Ack:
    """theta_k back to the encoder (Algorithms 1 and 2).

    ``last_rx`` is the latest sample whose symbol the decoder accepted (-1: none).
    An encoder that missed acks recovers theta of its one unacknowledged sample j
    from any later ack: theta_j = 0 iff last_rx == j (it sent nothing after j).
    """

    k: int
    stamp_ns: int
    theta: int
    last_rx: int

    def encode(self) -> tuple[bytes, bytes]:
        return _ACK.pack(self.theta, self.last_rx), Header(self.k, self.stamp_ns).encode()

    @classmethod
    def decode(cls, payload: object, attachment: object) -> Ack:
        h = Header.decode(attachment)
        data = _bytes(payload)
        if len(data) != _ACK.size:
            raise MessageError(f"ack of {len(data)} bytes, expected {_ACK.size}")
        theta, last_rx = _ACK.unpack(data)
        if theta > 1:
            raise MessageError(f"ack: theta = {theta} is not 0 or 1")
        return cls(h.k, h.stamp_ns, theta, last_rx)


# ============================================================================ telemetry
_VEC: dict[int, struct.Struct] = {}  # length-prefixed float64 vectors, one compiled struct per length


def _vec(v) -> bytes:
    n = len(v)
    s = _VEC.get(n)
    if s is None:
        if n > 255:
            raise MessageError("vector longer than 255")
        s = _VEC[n] = struct.Struct(f"<B{n}d")
    try:
        return s.pack(n, *v)
    except struct.error as e:
        raise MessageError(f"vector: {e}") from None


def _unvec(data: bytes, off: int) -> tuple[tuple[float, ...], int]:
    if off >= len(data):
        raise MessageError("truncated telemetry")
    n = data[off]
    end = off + 1 + 8 * n
    if end > len(data):
        raise MessageError("truncated telemetry vector")
    return struct.unpack_from(f"<{n}d", data, off + 1), end


class _Telemetry:
    """Binary telemetry: a fixed struct of scalars followed by length-prefixed float64 vectors."""

    _scalars: ClassVar[struct.Struct]
    _scalar_fields: ClassVar[tuple[str, ...]]
    _vector_fields: ClassVar[tuple[str, ...]]
    _optional_vector: ClassVar[str | None] = None  # a last vector sent only when not empty (then absent: ())

    def encode(self) -> bytes:
        out = self._scalars.pack(*[getattr(self, f) for f in self._scalar_fields])
        for f in self._vector_fields:
            out += _vec(getattr(self, f))
        if self._optional_vector is not None and getattr(self, self._optional_vector):
            out += _vec(getattr(self, self._optional_vector))
        return out

    @classmethod
    def decode(cls, payload):
        data = _bytes(payload)
        if len(data) < cls._scalars.size:
            raise MessageError(f"{cls.__name__}: {len(data)} bytes is too short")
        vals = dict(zip(cls._scalar_fields, cls._scalars.unpack_from(data, 0)))
        off = cls._scalars.size
        for f in cls._vector_fields:
            vals[f], off = _unvec(data, off)
        if cls._optional_vector is not None and off < len(data):
            vals[cls._optional_vector], off = _unvec(data, off)
            if not vals[cls._optional_vector]:  # never sent empty: an empty one is a trailing byte
                raise MessageError(f"{cls.__name__}: {len(data) - off + 1} trailing bytes")
        if off != len(data):
            raise MessageError(f"{cls.__name__}: {len(data) - off} trailing bytes")
        return cls(**vals)

    def to_dict(self) -> dict:
        return asdict(self)  # type: ignore[call-overload]  # every subclass is a dataclass


@dataclass(frozen=True, slots=True)
class PlantTelemetry(_Telemetry):
    """Plant, sample k: x_k taken at ``t_ns`` (the sampling instant: at or just after k T_ns), the u that acted over [t_k, t_k+1).

    ``u_rx_ns``: arrival of u_k (NO_TIME if it never came); ``theta`` as received
    (THETA_NONE if u_k never came); ``flags``: bit 0 deadline miss, bit 1 u_k
    missing (u = 0 applied), bit 2 controller known dead, bit 3 final state x_N
    (then u is empty); ``flow_status``: FLOW_* of phi_T for this period;
    ``delay_ns``: physical timing, how long u_{k-1} still acted after t_k;
    ``x_meas``: what the sensor read of x_k (``[plant.sensor]``; empty, and not sent, without one).
    """

    FLAG_MISS: ClassVar[int] = 1
    FLAG_NO_U: ClassVar[int] = 2
    FLAG_CTRL_DEAD: ClassVar[int] = 4
    FLAG_FINAL: ClassVar[int] = 8
    _scalars: ClassVar[struct.Struct] = struct.Struct("<IqqqqBBb")
    _scalar_fields: ClassVar[tuple[str, ...]] = ("k", "t_ns", "sensor_tx_ns", "u_rx_ns", "delay_ns",
                                                "theta", "flags", "flow_status")
    _vector_fields: ClassVar[tuple[str, ...]] = ("x", "u")
    _optional_vector: ClassVar[str | None] = "x_meas"

    k: int
    t_ns: int
    sensor_tx_ns: int
    u_rx_ns: int
    delay_ns: int
    theta: int
    flags: int
    flow_status: int
    x: tuple[float, ...]
    u: tuple[float, ...]
    x_meas: tuple[float, ...] = ()


@dataclass(frozen=True, slots=True)
class EncoderTelemetry(_Telemetry):
    """Encoder, sample k (Algorithm 1): xi_k, E_k, the symbol sent (-1: none sent), q_k at the encoder.

    ``silent``: the symbol was withheld because theta of an earlier sample was
    unknown (missing ack); xi, E, q are then empty.
    """

    _scalars: ClassVar[struct.Struct] = struct.Struct("<IqqqiBBd")
    _scalar_fields: ClassVar[tuple[str, ...]] = ("k", "sensor_tx_ns", "rx_ns", "tx_ns", "symbol",
                                                "saturated", "silent", "E")
    _vector_fields: ClassVar[tuple[str, ...]] = ("xi", "q")

    k: int
    sensor_tx_ns: int
    rx_ns: int
    tx_ns: int
    symbol: int
    saturated: int
    silent: int
    E: float
    xi: tuple[float, ...]
    q: tuple[float, ...]


@dataclass(frozen=True, slots=True)
class ControllerTelemetry(_Telemetry):
    """Controller, sample k (Algorithm 2, law (2)): xi_k, E_k before the update, theta_k, q_k, u_k.

    ``reason``: 0 received, 1 not received by the loss deadline, 2 invalid
    payload, 3 superseded (a later sample arrived first).
    """

    RECEIVED: ClassVar[int] = 0
    DEADLINE: ClassVar[int] = 1
    INVALID: ClassVar[int] = 2
    SUPERSEDED: ClassVar[int] = 3
    _scalars: ClassVar[struct.Struct] = struct.Struct("<IqqqiBBd")
    _scalar_fields: ClassVar[tuple[str, ...]] = ("k", "sym_stamp_ns", "rx_ns", "tx_ns", "symbol",
                                                "theta", "reason", "E")
    _vector_fields: ClassVar[tuple[str, ...]] = ("xi", "q", "u")

    k: int
    sym_stamp_ns: int
    rx_ns: int
    tx_ns: int
    symbol: int
    theta: int
    reason: int
    E: float
    xi: tuple[float, ...]
    q: tuple[float, ...]
    u: tuple[float, ...]


@dataclass(frozen=True, slots=True)
class AttackerTelemetry(_Telemetry):
    """Attacker proxy, sample k: dropped or forwarded (``tx_ns`` NO_TIME when dropped)."""

    _scalars: ClassVar[struct.Struct] = struct.Struct("<IqqBBBII")
    _scalar_fields: ClassVar[tuple[str, ...]] = ("k", "rx_ns", "tx_ns", "dropped", "corrupted",
                                                "attack_on", "dropped_total", "forwarded_total")
    _vector_fields: ClassVar[tuple[str, ...]] = ()

    k: int
    rx_ns: int
    tx_ns: int
    dropped: int
    corrupted: int
    attack_on: int
    dropped_total: int
    forwarded_total: int


def pack_batch(records: list[bytes]) -> bytes:
    """Several telemetry records in one payload (uint16 length before each)."""
    out = bytearray()
    for r in records:
        if len(r) > 0xFFFF:
            raise MessageError("telemetry record longer than 65535 bytes")
        out += struct.pack("<H", len(r))
        out += r
    return bytes(out)


def unpack_batch(payload: object) -> list[bytes]:
    data = _bytes(payload)
    out, off = [], 0
    while off < len(data):
        if off + 2 > len(data):
            raise MessageError("truncated telemetry batch")
        (n,) = struct.unpack_from("<H", data, off)
        off += 2
        if off + n > len(data):
            raise MessageError("truncated telemetry batch record")
        out.append(data[off:off + n])
        off += n
    return out


TELEMETRY_TYPES: dict[str, type[_Telemetry]] = {"plant": PlantTelemetry, "encoder": EncoderTelemetry,
                   "controller": ControllerTelemetry, "attacker": AttackerTelemetry}


# ============================================================================ bookkeeping (JSON)
class _Json:
    def encode(self) -> bytes:
        d = asdict(self)  # type: ignore[call-overload]  # every subclass is a dataclass
        return json.dumps(d, separators=(",", ":"), allow_nan=False, default=_json_default).encode()

    @classmethod
    def decode(cls, payload):
        try:
            d = json.loads(_bytes(payload))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise MessageError(f"{cls.__name__}: not JSON: {e}") from None
        if not isinstance(d, dict):
            raise MessageError(f"{cls.__name__}: not a JSON object")
        try:
            return cls(**d)
        except TypeError as e:
            raise MessageError(f"{cls.__name__}: {e}") from None


def _json_default(o):
    if hasattr(o, "tolist"):
        return o.tolist()
    if hasattr(o, "item"):
        return o.item()
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


@dataclass(frozen=True)
class Start(_Json):
    """The run's start: t0 on CLOCK_REALTIME (ns) and what every node must agree on.

    ``digest`` hashes the scenario text and the run options; a node whose own
    digest differs refuses to run.  ``protocol``: the wire protocol's version
    (``PROTOCOL_VERSION``); ``decode`` checks it first, before any other field, and
    raises ``ProtocolMismatch`` for another version (or for a Start without one).
    """

    run_id: str
    t0_ns: int
    T_ns: int
    n_steps: int
    digest: str
    timing: str
    ack_via_attacker: bool
    protocol: int = PROTOCOL_VERSION

    @classmethod
    def decode(cls, payload: object) -> Start:
        try:
            d = json.loads(_bytes(payload))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise MessageError(f"Start: not JSON: {e}") from None
        if not isinstance(d, dict):
            raise MessageError("Start: not a JSON object")
        theirs = d.get("protocol", 0)
        if theirs != PROTOCOL_VERSION or isinstance(theirs, bool):
            raise ProtocolMismatch(theirs)
        return super().decode(payload)


@dataclass(frozen=True)
class Stop(_Json):
    reason: str
    origin: str = ""


@dataclass(frozen=True)
class Event(_Json):
    """Something worth a line in the log: a fault, a saturation, a peer lost, ..."""

    node: str
    kind: str
    k: int = -1
    t_ns: int = NO_TIME
    detail: str = ""


@dataclass(frozen=True)
class AttackerStatus(_Json):
    """Published by the attacker proxy whenever the attack switches on or off."""

    k: int
    attack_on: bool
    dropped: int
    forwarded: int
    acks_dropped: int = 0


@dataclass(frozen=True)
class NodeSummary(_Json):
    """A node's counters and timing statistics, published once at exit."""

    node: str
    data: dict[str, Any] = field(default_factory=dict)

