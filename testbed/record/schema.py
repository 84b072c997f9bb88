"""Protobuf schemas of a recording (package ``testbed``), built in code: no ``protoc`` step.

Every MCAP channel of a recording carries one of the messages below, encoded
as protobuf (schema encoding ``protobuf``: a serialized ``FileDescriptorSet``,
what Foxglove and Rerun read).  The fields mirror the dataclasses of
``testbed.wire.messages`` one for one, with the same names, so converting is a
loop over field names (``to_pb`` / ``from_pb``).  Time stamps ``*_ns`` are
integer nanoseconds since the run's t0 (``RunStart.t0_ns``, CLOCK_REALTIME);
a time that never happened (``messages.NO_TIME``) is an *absent* field (proto3
``optional``), not a sentinel number.

Field types: ``u32`` uint32, ``i32`` int32, ``i64`` int64, ``f64`` double,
``bool``, ``str`` string, ``bytes``, ``ts`` ``google.protobuf.Timestamp`` (an
absolute time), ``hdr`` a ``testbed.Header`` (its ``stamp``: the field
Foxglove's and Lichtblick's Plot panels read as the "header stamp" of a
message, for their x axis); a trailing ``?`` is proto3 ``optional``, ``*`` is
``repeated`` (packed).  The spec below is the documentation of every
field; the README's recording section points here.
"""

from __future__ import annotations

from functools import cache, lru_cache
from typing import TYPE_CHECKING, Any

from ..common.protobuf import classes_from
from ..wire import messages as msg

if TYPE_CHECKING:
    from google.protobuf.message import Message

PACKAGE = "testbed"
FILE_NAME = "testbed/recording.proto"

#: message name -> [(field, type, what it means)]
SPEC: dict[str, list[tuple[str, str, str]]] = {
    # ---- per-sample telemetry (one message per sample k, topic /telemetry/<node>)
    "PlantSample": [
        ("k", "u32", "sample index"),
        ("t_ns", "i64?", "when x_k was sampled (nominal k*T_ns in simulation)"),
        ("sensor_tx_ns", "i64?", "when x_k was sent to the encoder"),
        ("u_rx_ns", "i64?", "when u_k arrived (absent: never arrived, u = 0 applied)"),
        ("delay_ns", "i64", "physical timing: how long u_{k-1} still acted after t_k"),
        ("theta", "u32", "theta_k as received with u_k (255: u_k never arrived)"),
        ("flags", "u32", "bit 0 deadline miss, 1 u_k missing, 2 controller known dead, 3 final state x_N"),
        ("flow_status", "i32", "status of the flow map phi_T over this period (0 ok)"),
        ("x", "f64*", "plant state x_k"),
        ("u", "f64*", "input applied over [t_k, t_k+1) (empty for the final state)"),
        ("header", "hdr", "header.stamp = t_k = t0 + k T, the sample instant, absolute (a Plot panel's x axis)"),
        ("x_meas", "f64*", "what the sensor read of x_k, sent to the encoder ([plant.sensor]; empty: x_k itself)"),
    ],
    "EncoderSample": [
        ("k", "u32", "sample index"),
        ("sensor_tx_ns", "i64?", "plant's send time of x_k"),
        ("rx_ns", "i64?", "when x_k reached the encoder"),
        ("tx_ns", "i64?", "when the symbol left the encoder (absent: nothing sent)"),
        ("symbol", "i32", "code sent (-1: none); M^n is OVERFLOW in resilient mode"),
        ("saturated", "bool", "x_k was outside Q(xi_k, E_k)"),
        ("silent", "bool", "symbol withheld (theta of an earlier sample unknown); xi, E, q empty"),
        ("E", "f64", "E_k at the encoder (Algorithm 1)"),
        ("xi", "f64*", "xi_k at the encoder"),
        ("q", "f64*", "q_k at the encoder"),
        ("header", "hdr", "header.stamp = t_k = t0 + k T, absolute"),
        ("log10_E", "f64?", "log10 E_k (absent when E_k is 0 or not sent): E_k spans tens of decades"),
    ],
    "ControllerSample": [
        ("k", "u32", "sample index"),
        ("sym_stamp_ns", "i64?", "encoder's stamp of the symbol received"),
        ("rx_ns", "i64?", "when the symbol arrived"),
        ("tx_ns", "i64?", "when u_k was sent"),
        ("symbol", "i32", "code received (-1: none)"),
        ("theta", "u32", "theta_k: 1 = no valid symbol by the deadline (DoS)"),
        ("reason", "u32", "0 received, 1 deadline, 2 invalid payload, 3 superseded"),
        ("E", "f64", "E_k at the decoder, before the update (Algorithm 2)"),
        ("xi", "f64*", "xi_k at the decoder"),
        ("q", "f64*", "q_k at the decoder"),
        ("u", "f64*", "u_k = (1 - theta_k) K q_k"),
        ("header", "hdr", "header.stamp = t_k = t0 + k T, absolute"),
        ("log10_E", "f64?", "log10 E_k at the decoder (absent when E_k is 0)"),
    ],
    "AttackerSample": [
        ("k", "u32", "sample index"),
        ("rx_ns", "i64?", "when the symbol reached the proxy"),
        ("tx_ns", "i64?", "when it was forwarded (absent: dropped)"),
        ("dropped", "bool", "dropped by the DoS schedule"),
        ("corrupted", "bool", "payload corrupted (fault injection)"),
        ("attack_on", "bool", "the DoS schedule is active at t_k"),
        ("dropped_total", "u32", "symbols dropped so far"),
        ("forwarded_total", "u32", "symbols forwarded so far"),
        ("header", "hdr", "header.stamp = t_k = t0 + k T, absolute"),
    ],
    "Header": [("stamp", "ts", "an absolute time (t0 + k T for telemetry)")],
    # ---- control path as it crossed the network (topics /loop/...)
    "Sensor": [("k", "u32", "sample index"), ("stamp_ns", "i64", "send time"),
               ("x", "f64*", "x_k as the sensor read it (x_meas with [plant.sensor])")],
    "Symbol": [("k", "u32", "sample index"), ("stamp_ns", "i64", "send time"),
               ("data", "bytes", "the packed symbol bits exactly as sent (Codebook.pack)")],
    "Actuation": [("k", "u32", "sample index"), ("stamp_ns", "i64", "send time"),
                  ("theta", "u32", "theta_k"), ("u", "f64*", "u_k"),
                  ("last_rx", "i32", "the ack it carries: latest sample whose symbol the decoder accepted "
                                     "(-1 none; reads 0 in recordings that predate the field)")],
    "Ack": [("k", "u32", "sample index"), ("stamp_ns", "i64", "send time"), ("theta", "u32", "theta_k"),
            ("last_rx", "i32", "latest sample whose symbol the decoder accepted (-1 none)")],
    # ---- bookkeeping
    "RunStart": [("run_id", "str", "run identity (Zenoh key prefix testbed/<run_id>)"),
                 ("t0_ns", "i64", "t0 on CLOCK_REALTIME (ns since the epoch); every *_ns is relative to it"),
                 ("T_ns", "i64", "sampling period T"), ("n_steps", "i64", "samples planned"),
                 ("digest", "str", "hash of the scenario text and run options"),
                 ("timing", "str", "ideal | physical"), ("ack_via_attacker", "bool", "acks routed via the proxy"),
                 ("protocol", "u32", "wire protocol version, docs/protocol.md (0 in recordings that predate it)")],
    "RunStop": [("reason", "str", "why"), ("origin", "str", "who sent it")],
    "Event": [("node", "str", "publisher"), ("kind", "str", "saturation, malformed, peer_lost, killed, ..."),
              ("k", "i64", "sample index (-1: none)"), ("t_ns", "i64?", "when"), ("detail", "str", "free text")],
    "AttackerStatus": [("k", "u32", "sample at which the attack switched"), ("attack_on", "bool", "on or off"),
                       ("dropped", "u32", "symbols dropped so far"), ("forwarded", "u32", "forwarded so far"),
                       ("acks_dropped", "u32", "acks dropped so far")],
    "NodeSummary": [("node", "str", "node"), ("json", "str", "its counters and timing, a JSON object")],
    "Liveliness": [("node", "str", "node"), ("token", "str", "alive | ready"),
                   ("present", "bool", "token appeared (true) or went away (false)")],
    "Malformed": [("key", "str", "Zenoh key"), ("payload", "bytes", "payload as received"),
                  ("attachment", "bytes", "attachment as received"), ("error", "str", "why it did not decode")],
}

#: the messages dataclass behind a schema (the same field names)
DATACLASS = {
    "PlantSample": msg.PlantTelemetry, "EncoderSample": msg.EncoderTelemetry,
    "ControllerSample": msg.ControllerTelemetry, "AttackerSample": msg.AttackerTelemetry,
    "Sensor": msg.Sensor, "Symbol": msg.Symbol, "Actuation": msg.Actuation, "Ack": msg.Ack,
    "RunStart": msg.Start, "RunStop": msg.Stop, "Event": msg.Event, "AttackerStatus": msg.AttackerStatus,
}
SCHEMA_OF = {cls: name for name, cls in DATACLASS.items()}

_TYPES = {"u32": 13, "i32": 5, "i64": 3, "f64": 1, "bool": 8, "str": 9, "bytes": 12, "ts": 11,
          "hdr": 11}  # FieldDescriptorProto.Type
_MESSAGE_TYPES = {"ts": ".google.protobuf.Timestamp", "hdr": f".{PACKAGE}.Header"}
_TIMESTAMP_FILE = "google/protobuf/timestamp.proto"


def _file_descriptor():
    from google.protobuf import descriptor_pb2

    fd = descriptor_pb2.FileDescriptorProto(name=FILE_NAME, package=PACKAGE, syntax="proto3")
    fd.dependency.append(_TIMESTAMP_FILE)
    for name, fields in SPEC.items():
        m = fd.message_type.add(name=name)
        for number, (fname, ftype, _doc) in enumerate(fields, start=1):
            base = ftype.rstrip("?*")
            f = m.field.add(name=fname, number=number, type=_TYPES[base], json_name=fname)
            if base in _MESSAGE_TYPES:
                f.type_name = _MESSAGE_TYPES[base]
            if ftype.endswith("*"):
                f.label = f.LABEL_REPEATED
            else:
                f.label = f.LABEL_OPTIONAL
            if ftype.endswith("?"):
                f.proto3_optional = True
                f.oneof_index = len(m.oneof_decl)
                m.oneof_decl.add(name=f"_{fname}")
    # synthetic oneofs must come after the real ones; there are none, so the order above is fine
    return fd


@lru_cache(maxsize=1)
def file_descriptor_set() -> bytes:
    """The schema data stored in the MCAP file (one ``FileDescriptorSet`` for every message)."""
    from google.protobuf import descriptor_pb2, timestamp_pb2

    fds = descriptor_pb2.FileDescriptorSet()
    ts = fds.file.add()
    timestamp_pb2.DESCRIPTOR.CopyToProto(ts)   # the well-known type, so the set is self-contained
    fds.file.append(_file_descriptor())
    return fds.SerializeToString()


@lru_cache(maxsize=1)
def classes() -> dict[str, type[Message]]:
    """This version's message classes, by short name (``PlantSample`` ...)."""
    return {full.rsplit(".", 1)[-1]: cls for full, cls in classes_from(file_descriptor_set()).items()
            if full.startswith(PACKAGE + ".")}


def full_name(name: str) -> str:
    return f"{PACKAGE}.{name}"


@cache
def _layout(name: str):
    fields = SPEC[name]
    plain = tuple(f for f, t, _ in fields if not t.endswith(("?", "*")) and t not in _MESSAGE_TYPES)
    optional = tuple(f for f, t, _ in fields if t.endswith("?"))
    repeated = tuple(f for f, t, _ in fields if t.endswith("*"))
    stamps = tuple(f for f, t, _ in fields if t == "ts")
    headers = tuple(f for f, t, _ in fields if t == "hdr")
    return plain, optional, repeated, stamps, headers


def to_pb(obj: Any, name: str | None = None, extra: dict | None = None) -> Any:
    """A messages dataclass (or a dict with the schema's field names) -> protobuf message.

    ``extra``: fields the dataclass does not have (``header``: its stamp in ns since the epoch, ``log10_E``).
    """
    if name is None:
        name = SCHEMA_OF[type(obj)]
    if isinstance(obj, dict):
        get = obj.get if not extra else {**obj, **extra}.get
    else:
        def get(f, _o=obj, _x=extra or {}):
            return _x[f] if f in _x else getattr(_o, f, None)
    plain, optional, repeated, stamps, headers = _layout(name)
    m = classes()[name]()
    for f in plain:
        v = get(f)
        if v is not None:
            setattr(m, f, v)
    for f in optional:
        v = get(f)
        if v is not None and v != msg.NO_TIME:
            setattr(m, f, v)
    for f in repeated:
        v = get(f)
        if v:
            getattr(m, f).extend(v)
    for f in stamps:
        v = get(f)
        if v is not None and v != msg.NO_TIME:
            ts = getattr(m, f)
            ts.seconds, ts.nanos = divmod(int(v), 1_000_000_000)
    for f in headers:
        v = get(f)
        if v is not None and v != msg.NO_TIME:
            ts = getattr(m, f).stamp
            ts.seconds, ts.nanos = divmod(int(v), 1_000_000_000)
    return m


@cache
def _converter(name: str):
    """protobuf message -> dataclass, fields read in the dataclass's order (the hot path of reading)."""
    import dataclasses

    cls = DATACLASS[name]
    kinds = {f: t[-1] if t[-1] in "?*" else "" for f, t, _ in SPEC[name]}
    order = [(f.name, kinds[f.name]) for f in dataclasses.fields(cls)]
    # one straight-line expression per schema (generated from SPEC, our own names): ~3x a generic loop
    parts = [f"m.{f}" if kind == "" else f"(m.{f} if m.HasField({f!r}) else NO)" if kind == "?" else
             f"tuple(m.{f})" for f, kind in order]
    env = {"cls": cls, "NO": msg.NO_TIME}
    exec(f"def conv(m):\n    return cls({', '.join(parts)})\n", env)  # noqa: S102 - trusted, generated
    return env["conv"]


def from_pb(m: Any, name: str) -> Any:
    """protobuf message -> the messages dataclass of its schema."""
    return _converter(name)(m)


def describe() -> str:
    """Markdown tables of every message and field (for the README)."""
    lines = []
    for name, fields in SPEC.items():
        lines.append(f"**`{full_name(name)}`**\n\n| field | type | meaning |\n|---|---|---|")
        for f, t, doc in fields:
            lines.append(f"| `{f}` | {t} | {doc} |")
        lines.append("")
    return "\n".join(lines)
