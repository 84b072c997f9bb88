"""The generated parts of docs/protocol.md: key table, byte layouts, JSON fields, the worked example.

docs/protocol.md is written by hand except for the blocks between
``<!-- BEGIN generated:NAME -->`` and ``<!-- END generated:NAME -->``, which this module
makes from the definitions themselves (``testbed.wire.messages``, ``testbed.wire.transport``)
and, for the worked example, from the real encoders and state machines of the nodes
(``testbed.loop.protocol`` on the bundled ``paper`` scenario).  ``python -m testbed.wire.spec``
rewrites the blocks of docs/protocol.md; ``--check`` only says whether they are current
(tests/wire/test_protocol_spec.py does the same).  Every field of every message needs a line in
``FIELD_DOC`` here: a new field without one fails the generator, so the spec cannot miss it.
"""

from __future__ import annotations

import dataclasses
import re
import struct
import sys
from collections.abc import Sequence
from pathlib import Path

from . import messages as msg
from . import transport

#: struct code -> (wire type, size in bytes)
_CODES = {"B": ("uint8", 1), "b": ("int8", 1), "H": ("uint16", 2), "i": ("int32", 4), "I": ("uint32", 4),
          "q": ("int64", 8), "d": ("float64", 8)}

#: (class name, field) -> "unit or range | meaning"; one line per field of every message
FIELD_DOC = {
    ("Header", "k"): ("0 .. N-1; 4294967295 = warm-up", "sample index k (WARMUP_K: a warm-up put before t0, ignore it)"),
    ("Header", "stamp_ns"): ("ns since t0", "the sender's run clock when it sent the message (Sensor: the instant x_k "
                                            "was sampled, the plant's run clock on waking for t_k, at or just after k T, "
                                            "the same number as PlantTelemetry t_ns; a forwarded Symbol or Ack keeps the "
                                            "original header)"),
    ("Sensor", "x"): ("n x float64", "x_k, the plant's state sampled at t_k, as its sensor read it ([plant.sensor])"),
    ("Symbol", "data"): ("ceil(bits/8) bytes, big-endian", "the symbol i, 0 <= i < n_codes (M^n, + 1 for OVERFLOW)"),
    ("Actuation", "theta"): ("0 or 1", "theta_k: 0 the symbol of sample k was accepted, 1 it was not"),
    ("Actuation", "last_rx"): ("-1 .. k", "the latest sample whose symbol the decoder accepted (-1: none)"),
    ("Actuation", "u"): ("m x float64", "u_k = (1 - theta_k) K q_k"),
    ("Ack", "theta"): ("0 or 1", "theta_k, as in Actuation"),
    ("Ack", "last_rx"): ("-1 .. k", "as in Actuation"),
    # telemetry
    ("PlantTelemetry", "k"): ("0 .. N", "sample index (N: the final record, flag bit 3)"),
    ("PlantTelemetry", "t_ns"): ("ns since t0", "the instant x_k was sampled: the plant's run clock when it woke "
                                          "for t_k (at or just after k T; not k T itself), the Sensor header's "
                                          "stamp; the final record: when it was written"),
    ("PlantTelemetry", "sensor_tx_ns"): ("ns since t0", "when x_k was published"),
    ("PlantTelemetry", "u_rx_ns"): ("ns since t0, or NO_TIME", "arrival of u_k (NO_TIME: never came)"),
    ("PlantTelemetry", "delay_ns"): ("0 .. T", "physical timing: how long u_(k-1) still acted after t_k (0 in ideal)"),
    ("PlantTelemetry", "theta"): ("0, 1 or 255", "theta_k as received (255: u_k never came)"),
    ("PlantTelemetry", "flags"): ("bit set", "bit 0 deadline miss, 1 u_k missing (u = 0 applied), 2 controller dead, "
                                             "3 final record (x_N, u empty)"),
    ("PlantTelemetry", "flow_status"): ("0, 1 or 2", "status of the flow map phi_T over this period: 0 ok, 1 "
                                                           "diverged, 2 step limit (Flow map); the final record: "
                                                           "the run's last status"),
    ("PlantTelemetry", "x"): ("n x float64", "x_k"),
    ("PlantTelemetry", "u"): ("m x float64", "the u that acted over [t_k, t_k+1) (empty in the final record)"),
    ("PlantTelemetry", "x_meas"): ("n x float64, optional", "what the sensor read of x_k ([plant.sensor]); not sent "
                                                            "(the message ends after u) without a sensor"),
    ("EncoderTelemetry", "k"): ("0 .. N-1", "sample index"),
    ("EncoderTelemetry", "sensor_tx_ns"): ("ns since t0", "the sensor message's stamp"),
    ("EncoderTelemetry", "rx_ns"): ("ns since t0", "arrival of x_k"),
    ("EncoderTelemetry", "tx_ns"): ("ns since t0, or NO_TIME", "when the symbol was published (NO_TIME: withheld)"),
    ("EncoderTelemetry", "symbol"): ("-1 .. n_codes-1", "the symbol sent (-1: none)"),
    ("EncoderTelemetry", "saturated"): ("0 or 1", "x_k was outside Q(xi_k, E_k)"),
    ("EncoderTelemetry", "silent"): ("0 or 1", "withheld: theta of an earlier sample unknown (xi, E, q then empty/NaN)"),
    ("EncoderTelemetry", "E"): ("float64", "E_k, the encoder's box half-width for sample k (NaN when silent)"),
    ("EncoderTelemetry", "xi"): ("n x float64", "xi_k, the box centre"),
    ("EncoderTelemetry", "q"): ("n x float64", "q_k at the encoder"),
    ("ControllerTelemetry", "k"): ("0 .. N-1", "sample index"),
    ("ControllerTelemetry", "sym_stamp_ns"): ("ns since t0, or NO_TIME", "the symbol's header stamp (NO_TIME: none)"),
    ("ControllerTelemetry", "rx_ns"): ("ns since t0, or NO_TIME", "arrival of the symbol"),
    ("ControllerTelemetry", "tx_ns"): ("ns since t0", "when u_k was published"),
    ("ControllerTelemetry", "symbol"): ("-1 .. n_codes-1", "the code received (-1: none)"),
    ("ControllerTelemetry", "theta"): ("0 or 1", "theta_k"),
    ("ControllerTelemetry", "reason"): ("0 .. 3", "0 received, 1 loss deadline, 2 invalid payload, 3 superseded"),
    ("ControllerTelemetry", "E"): ("float64", "E_k before the update"),
    ("ControllerTelemetry", "xi"): ("n x float64", "xi_k before the update"),
    ("ControllerTelemetry", "q"): ("n x float64", "q_k"),
    ("ControllerTelemetry", "u"): ("m x float64", "u_k"),
    ("AttackerTelemetry", "k"): ("0 .. N-1", "sample index"),
    ("AttackerTelemetry", "rx_ns"): ("ns since t0", "arrival of the symbol"),
    ("AttackerTelemetry", "tx_ns"): ("ns since t0, or NO_TIME", "when it was forwarded (NO_TIME: dropped)"),
    ("AttackerTelemetry", "dropped"): ("0 or 1", "the symbol was dropped"),
    ("AttackerTelemetry", "corrupted"): ("0 or 1", "fault injection: the payload was corrupted"),
    ("AttackerTelemetry", "attack_on"): ("0 or 1", "the attack was on at t_k"),
    ("AttackerTelemetry", "dropped_total"): ("count", "symbols dropped so far"),
    ("AttackerTelemetry", "forwarded_total"): ("count", "symbols forwarded so far"),
    # JSON
    ("Start", "run_id"): ("string", "the run's id: the key prefix is testbed/<run_id>"),
    ("Start", "t0_ns"): ("ns since the Unix epoch, CLOCK_REALTIME", "t0, the instant of sample 0"),
    ("Start", "T_ns"): ("ns > 0", "the sampling period T"),
    ("Start", "n_steps"): ("N > 0", "samples of the run: k = 0 .. N-1"),
    ("Start", "digest"): ("16 hex digits", "hash of the scenario text and run options (see Run identity)"),
    ("Start", "timing"): ('"ideal" or "physical"', "the plant's timing mode"),
    ("Start", "ack_via_attacker"): ("bool", "theta_k reaches the encoder through the attacker (loop/ack/rx)"),
    ("Start", "protocol"): ("integer", "the wire protocol's version (see Versioning)"),
    ("Stop", "reason"): ("string", "why the run stops"),
    ("Stop", "origin"): ('"plant" or "launcher"', "who stops it; any other origin is ignored"),
    ("Event", "node"): ("role", "the publisher"),
    ("Event", "kind"): ("string", "malformed, late_symbol, future_*, peer_lost, saturation, ..."),
    ("Event", "k"): ("-1 .. N", "sample index (-1: none)"),
    ("Event", "t_ns"): ("ns since t0, or NO_TIME", "when"),
    ("Event", "detail"): ("string", "free text"),
    ("AttackerStatus", "k"): ("0 .. N-1", "sample at which the attack switched"),
    ("AttackerStatus", "attack_on"): ("bool", "on or off"),
    ("AttackerStatus", "dropped"): ("count", "symbols dropped so far"),
    ("AttackerStatus", "forwarded"): ("count", "symbols forwarded so far"),
    ("AttackerStatus", "acks_dropped"): ("count", "acks dropped so far"),
    ("NodeSummary", "node"): ("role", "the publisher"),
    ("NodeSummary", "data"): ("object", "its counters and timing (free form, for humans and the launcher)"),
}

#: key (after the prefix) -> (who reads it, message, when); who publishes it comes from the access rules
KEY_DOC = {
    "loop/sensor": ("encoder (attacker: greedy, score state)", "Sensor", "every sample, at t_k"),
    "loop/symbol/tx": ("attacker", "Symbol", "every sample the encoder does not withhold"),
    "loop/symbol/rx": ("controller", "Symbol", "every symbol the attacker forwards (payload and header unchanged)"),
    "loop/actuation": ("plant; encoder (ideal ack)", "Actuation", "every sample, once decided"),
    "loop/ack/tx": ("encoder (--separate-ack) or attacker (--ack-via-attacker)", "Ack",
                    "every sample, unless the ack rides on the actuation"),
    "loop/ack/rx": ("encoder (--ack-via-attacker)", "Ack", "every ack the attacker forwards"),
    "control/start": ("every node, recorder, launcher", "Start", "every 50 ms from readiness until 20 ms before t0"),
    "control/stop": ("every node, recorder, launcher", "Stop", "once, at the end (or on a fault)"),
    "attacker/status": ("recorder, launcher", "AttackerStatus", "whenever the attack switches"),
    "telemetry/<role>": ("recorder, launcher (attacker: encoder's, greedy score E)", "batch of <Role>Telemetry",
                         "every sample, batched (<= 20 ms of samples per message)"),
    "events/<node>": ("recorder, launcher", "Event", "on faults, saturations, ... (<= 20 per s per kind)"),
    "summary/<node>": ("recorder, launcher", "NodeSummary", "once, at exit"),
    "collector/summaries": ("every node that sees alive/collector (a query, after its summary)", "JSON list of roles",
                            "a reply to each query: the roles whose NodeSummary the collector holds"),
    "alive/<node>": ("every process (liveliness)", "liveliness token", "from warm-up to exit"),
    "ready/<node>": ("every process (liveliness)", "liveliness token", "once the node is warm and sees its peers"),
    "recorder/stats": ("launcher", "JSON", "the recorder's counters"),
}


def _generic(key: str) -> str:
    """``telemetry/plant`` -> ``telemetry/<role>``, ``alive/collector`` -> ``alive/<node>``."""
    return re.sub(r"/(plant|encoder|attacker|controller|recorder|launcher|collector)$",
                  "/<role>" if key.startswith("telemetry/") else "/<node>", key)


def _publishers(key: str) -> list[str]:
    """Who may publish ``key``, by the access rules (``transport.publish_keys``)."""
    return [u for u in transport.USERS if key in {_generic(k) for k in transport.publish_keys(u)}]


def keys_table() -> str:
    rows = ["| key (after `testbed/<run_id>/`) | published by | read by | message | when |", "|---|---|---|---|---|"]
    for key, (readers, message, when) in KEY_DOC.items():
        pubs = _publishers(key)
        if not pubs:
            raise AssertionError(f"no process may publish {key}: KEY_DOC and transport.publish_keys disagree")
        who = ", ".join(pubs)
        if key.endswith(">"):
            who = f"each of {who}, under its own name"
        rows.append(f"| `{key}` | {who} | {readers} | {message} | {when} |")
    for u in transport.USERS:
        for k in transport.publish_keys(u):
            if _generic(k) not in KEY_DOC:
                raise AssertionError(f"{u} may publish {k}, which the spec does not list (KEY_DOC)")
    return "\n".join(rows)


def _struct_rows(cls_name: str, st: struct.Struct, names: Sequence[str], off0: int = 0) -> tuple[list[str], int]:
    fmt = st.format.lstrip("<")
    if st.format[0] != "<":
        raise AssertionError(f"{cls_name}: {st.format} is not little-endian")
    rows, off = [], off0
    for code, name in zip(fmt, names, strict=True):
        t, size = _CODES[code]
        unit, meaning = FIELD_DOC[(cls_name, name)]
        rows.append(f"| {off} | {size} | {t} | `{name}` | {unit} | {meaning} |")
        off += size
    return rows, off


_HEAD = ["| offset | bytes | type | field | unit / range | meaning |", "|---|---|---|---|---|---|"]


def layouts() -> str:
    """Header, Sensor, Symbol, Actuation and Ack: byte by byte."""
    out = ["**Header** (the Zenoh attachment of every control-path message, "
           f"{msg.HEADER_SIZE} bytes, `struct` format `{msg._HEADER.format}`)", "", *_HEAD]
    out += _struct_rows("Header", msg._HEADER, ("k", "stamp_ns"))[0]
    unit, meaning = FIELD_DOC[("Sensor", "x")]
    out += ["", "**Sensor** payload (n x 8 bytes)", "", *_HEAD, f"| 0 | 8 n | float64[n] | `x` | {unit} | {meaning} |"]
    unit, meaning = FIELD_DOC[("Symbol", "data")]
    out += ["", "**Symbol** payload", "", *_HEAD, f"| 0 | ceil(bits / 8) | uint, big-endian | `data` | {unit} | {meaning} |"]
    for name, st in (("Actuation", msg._ACT), ("Ack", msg._ACK)):
        rows, off = _struct_rows(name, st, ("theta", "last_rx"))
        size = f"{off} + 8 m bytes" if name == "Actuation" else f"{off} bytes"
        out += ["", f"**{name}** payload ({size}, `struct` format `{st.format}`"
                + (" + m float64" if name == "Actuation" else "") + ")", "", *_HEAD, *rows]
        if name == "Actuation":
            unit, meaning = FIELD_DOC[("Actuation", "u")]
            out.append(f"| {off} | 8 m | float64[m] | `u` | {unit} | {meaning} |")
    _check_fields()
    return "\n".join(out)


def telemetry_layouts() -> str:
    out = []
    for role, cls in msg.TELEMETRY_TYPES.items():
        rows, off_n = _struct_rows(cls.__name__, cls._scalars, cls._scalar_fields)
        off: int | str = off_n
        for f in cls._vector_fields + ((cls._optional_vector,) if cls._optional_vector else ()):
            unit, meaning = FIELD_DOC[(cls.__name__, f)]
            rows.append(f"| {off if isinstance(off, int) else off} | 1 + 8 len | uint8 len, float64[len] | `{f}` | "
                        f"{unit} | {meaning} |")
            off = "..."
        out += [f"**{cls.__name__}** (`telemetry/{role}`, scalars `{cls._scalars.format}` = {cls._scalars.size} bytes"
                + (", then length-prefixed vectors" if cls._vector_fields else "") + ")", "", *_HEAD, *rows, ""]
    return "\n".join(out).rstrip()


def json_fields() -> str:
    out = []
    for cls in (msg.Start, msg.Stop, msg.Event, msg.AttackerStatus, msg.NodeSummary):
        out += [f"**{cls.__name__}**", "", "| field | JSON type | unit / range | meaning |", "|---|---|---|---|"]
        for f in dataclasses.fields(cls):
            unit, meaning = FIELD_DOC[(cls.__name__, f.name)]
            t = {"int": "integer", "str": "string", "bool": "true/false"}.get(str(f.type), "object")
            default = "" if f.default is dataclasses.MISSING else f" (optional, default {_json_default(f.default)})"
            if cls is msg.Start and f.name == "protocol":
                default = " (required: a Start without it is refused as version 0)"
            out.append(f"| `{f.name}` | {t}{default} | {unit} | {meaning} |")
        out.append("")
    return "\n".join(out).rstrip()


def _json_default(v: object) -> str:
    if v == msg.NO_TIME:
        return "NO_TIME"
    return "`\"\"`" if v == "" else f"`{v}`"


def _check_fields() -> None:
    """Every field of every message has its line in FIELD_DOC (and no stale line is left)."""
    classes = [msg.Header, msg.Sensor, msg.Symbol, msg.Actuation, msg.Ack, *msg.TELEMETRY_TYPES.values(),
               msg.Start, msg.Stop, msg.Event, msg.AttackerStatus, msg.NodeSummary]
    want = set()
    for cls in classes:
        names = [f.name for f in dataclasses.fields(cls)]
        if cls in (msg.Sensor, msg.Symbol, msg.Actuation, msg.Ack):
            names = [n for n in names if n not in ("k", "stamp_ns")]  # in the header
        want |= {(cls.__name__, n) for n in names}
    missing, stale = want - set(FIELD_DOC), set(FIELD_DOC) - want
    if missing or stale:
        raise AssertionError(f"FIELD_DOC: fields without a line {sorted(missing)}, lines without a field {sorted(stale)}")


def constants() -> str:
    return "\n".join([
        "| constant | value | meaning |", "|---|---|---|",
        f"| `PROTOCOL_VERSION` | {msg.PROTOCOL_VERSION} | this protocol's version, in `Start.protocol` |",
        f"| `HEADER_SIZE` | {msg.HEADER_SIZE} | bytes of the header attachment |",
        f"| `WARMUP_K` | {msg.WARMUP_K} (0x{msg.WARMUP_K:08X}) | header k of a warm-up put: ignore the message |",
        f"| `NO_TIME` | {msg.NO_TIME} | an int64 time that never happened |",
        f"| `THETA_NONE` | {msg.THETA_NONE} | theta unknown (plant telemetry: u_k never came) |",
        f"| `MAX_MESSAGE_BYTES` | {transport.MAX_MESSAGE_BYTES} | a larger message is dropped by the receiving session |",
    ])


# ============================================================================ the worked example
#: illustrative times of sample 0 on the run clock (ns since t0); everything else is computed
EXAMPLE_TIMES = {"sampled": 12_000, "sensor_tx": 150_000, "encoder_rx": 260_000, "symbol_tx": 410_000,
                 "attacker_rx": 480_000, "forwarded": 520_000, "controller_rx": 600_000, "actuation_tx": 730_000,
                 "plant_rx": 800_000}


def example_messages() -> dict:
    """Sample 0 of the bundled ``paper`` scenario, by the nodes' own state machines: every
    message of the sample as (key, payload bytes, attachment bytes), and the numbers behind them."""
    from .. import scenario
    from ..loop.protocol import ControllerProtocol, EncoderProtocol, Send

    sc = scenario.load("paper")
    model = sc.make_model()
    method = sc.make_method()
    enc = method.make_encoder(model, sc.K, sc.quantizer, sc.flow)
    dec = method.make_decoder(model, sc.K, sc.quantizer, sc.flow)
    ep, cp = EncoderProtocol(enc, sc.n_steps), ControllerProtocol(dec, sc.n_steps)
    keys = transport.Keys.for_run("demo")
    x0 = tuple(float(v) for v in sc.x0)
    send = ep.sensor(0, x0)
    assert isinstance(send, Send)  # sample 0 of a fresh encoder is sent
    data = enc.codebook.pack(send.symbol)
    (d,) = cp.symbol(0, data)
    t = EXAMPLE_TIMES
    u = tuple(float(v) for v in d.u)
    sensor = msg.Sensor(0, t["sampled"], x0).encode()
    symbol = msg.Symbol(0, t["symbol_tx"], data).encode()
    act = msg.Actuation(0, t["actuation_tx"], d.theta, u, d.last_rx).encode()
    tel = {
        "plant": msg.PlantTelemetry(k=0, t_ns=t["sampled"], sensor_tx_ns=t["sensor_tx"], u_rx_ns=t["plant_rx"],
                                    delay_ns=0, theta=d.theta, flags=0, flow_status=0, x=x0, u=u),
        "encoder": msg.EncoderTelemetry(k=0, sensor_tx_ns=t["sampled"], rx_ns=t["encoder_rx"], tx_ns=t["symbol_tx"],
                                        symbol=int(send.symbol), saturated=int(send.saturated), silent=0,
                                        E=float(send.E), xi=tuple(send.xi.tolist()), q=tuple(send.q.tolist())),
        "attacker": msg.AttackerTelemetry(k=0, rx_ns=t["attacker_rx"], tx_ns=t["forwarded"], dropped=0, corrupted=0,
                                          attack_on=0, dropped_total=0, forwarded_total=1),
        "controller": msg.ControllerTelemetry(k=0, sym_stamp_ns=t["symbol_tx"], rx_ns=t["controller_rx"],
                                              tx_ns=t["actuation_tx"], symbol=int(d.symbol), theta=d.theta,
                                              reason=d.reason, E=float(d.E), xi=tuple(d.xi.tolist()),
                                              q=tuple(d.q.tolist()), u=u),
    }
    return {"scenario": sc, "x0": x0, "symbol": int(send.symbol), "E": float(send.E), "xi": tuple(send.xi.tolist()),
            "q": tuple(send.q.tolist()), "theta": d.theta, "last_rx": d.last_rx, "u": u,
            "M": enc.codebook.M, "n": model.n, "m": model.m, "telemetry": tel,
            "messages": [(keys.sensor, *sensor), (keys.symbol_tx, *symbol), (keys.symbol_rx, *symbol),
                         (keys.actuation, *act)]
            + [(keys.telemetry(r), msg.pack_batch([rec.encode()]), b"") for r, rec in tel.items()]}


def _wrapped(label: str, b: bytes, per_line: int = 24) -> list[str]:
    chunks = [b[i:i + per_line] for i in range(0, len(b), per_line)] or [b""]
    return [f"{label if i == 0 else '':<12}{_hex(c)}" for i, c in enumerate(chunks)]


def _hex(b: bytes) -> str:
    return " ".join(f"{c:02x}" for c in b) if b else "(empty)"


def example() -> str:
    e = example_messages()
    sc = e["scenario"]
    lines = [f"Run id `demo`, bundled scenario `paper` (n = {e['n']}, m = {e['m']}, M = {e['M']}, "
             f"T = {sc.T:g} s), sample k = 0, x_0 = {list(e['x0'])}. The encoder (Algorithm 1) with xi_0 = "
             f"{list(e['xi'])} and E_0 = {e['E']:g} sends symbol {e['symbol']}, the box whose centre is q_0 = "
             f"[{', '.join(f'{v:.17g}' for v in e['q'])}]; the controller accepts it (theta_0 = {e['theta']}, "
             f"last_rx = {e['last_rx']}) and sends u_0 = K q_0 = [{', '.join(f'{v!r}' for v in e['u'])}]. "
             f"The times are an example ({', '.join(f'{k} {v}' for k, v in EXAMPLE_TIMES.items())}, ns since t0); "
             f"at T = {sc.T:g} s each telemetry message holds one record (a batch of one: a uint16 length, then "
             "the record).",
             "", "```"]
    for key, payload, att in e["messages"]:
        lines += [f"key         {key}"] + ([f"attachment  {_hex(att)}"] if att else [])
        lines += _wrapped("payload", payload) + [""]
    lines[-1] = "```"
    return "\n".join(lines)


def join_fields() -> str:
    """The join file's fields (``testbed.wire.join.FIELDS``)."""
    from . import join

    rows = [f"| `{name}` | {typ} | {meaning} |" for name, typ, meaning in join.FIELDS]
    return "\n".join(["| field | JSON type | meaning |", "|---|---|---|", *rows])


def plant_flags() -> str:
    """The bits of ``PlantTelemetry.flags`` (``PlantTelemetry.FLAG_*``)."""
    PT = msg.PlantTelemetry
    rows = [(PT.FLAG_MISS, "deadline miss: no u_k by t_k + d T, u = 0 acted (with bit 1)"),
            (PT.FLAG_NO_U, "u_k missing: u = 0 acted (no actuation, a non-finite u_k, or the controller dead)"),
            (PT.FLAG_CTRL_DEAD, "controller dead: its `alive` token went; the plant no longer waits (with bit 1, "
                                "theta 255, never with bit 0)"),
            (PT.FLAG_FINAL, "the final record: x_N (k = N when the run completed), u empty")]
    out = ["| bit | value | meaning |", "|---|---|---|"]
    return "\n".join(out + [f"| {v.bit_length() - 1} | {v} | {m} |" for v, m in rows])


def flow_codes() -> str:
    """The ``flow_status`` codes (``testbed.loop.params.STATUS_NAMES``)."""
    from ..loop.params import FLOW_DIVERGED, FLOW_OK, FLOW_STEP_LIMIT, STATUS_NAMES

    meaning = {FLOW_OK: "the period was integrated to its end",
               FLOW_DIVERGED: "an accepted step had ||x||_inf > x_max (1e8): x is that step's state; the run ends",
               FLOW_STEP_LIMIT: "more than max_steps (20000) trial steps, or the step fell below 1e-15 T: x is the "
                                "last accepted state; the run ends"}
    rows = [f"| {c} | `{STATUS_NAMES[c]}` | {meaning[c]} |" for c in sorted(STATUS_NAMES)]
    return "\n".join(["| code | name | meaning |", "|---|---|---|", *rows])


def dop853_coefficients() -> str:
    """The stages and error estimators of ``testbed/loop/_dop853.py`` as written there (its float64 literals)."""
    src = (Path(__file__).resolve().parents[1] / "loop" / "_dop853.py").read_text()
    stages = re.findall(r"ytmp\[i\] = y\[i\] \+ h \* \((.*)\)\n", src)
    errs = dict(re.findall(r"(a[53]) = \((.*)\) / sc", src))
    if len(stages) != 12 or set(errs) != {"a5", "a3"}:
        raise AssertionError("testbed/loop/_dop853.py: 12 stages and two error sums expected")

    def expr(e: str) -> str:
        return re.sub(r"K\[(\d+), i\]", r"K\1", e).replace("+ -", "- ")

    lines = [f"stage {j:2d}: Y = y + h*({expr(e)}); K{j} = f(Y, u)" for j, e in enumerate(stages, 1)]
    lines[-1] = lines[-1].replace("Y = y", "ynew = y").replace("f(Y, u)", "f(ynew, u)")
    lines += [f"err5 sum:  ({expr(errs['a5'])}) / sc", f"err3 sum:  ({expr(errs['a3'])}) / sc"]
    return "```\n" + "\n".join(lines) + "\n```"


def acl_block() -> str:
    """The access control of a run (``transport.acl_config``) for run id ``RUN``, by certificate common name."""
    import json

    acl = transport.acl_config(transport.Keys.for_run("RUN"), by="cert_common_names")
    return "```json5\n" + json.dumps({"access_control": acl}, indent=1) + "\n```"


# ============================================================================ the document
BLOCKS = {"constants": constants, "keys": keys_table, "layouts": layouts, "telemetry": telemetry_layouts,
          "json": json_fields, "example": example, "join": join_fields, "flags": plant_flags, "flow_codes": flow_codes,
          "dop853": dop853_coefficients, "acl": acl_block}
_BLOCK = re.compile(r"(<!-- BEGIN generated:(\w+) -->\n)(.*?)(<!-- END generated:\2 -->)", re.S)
DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"


def render(text: str) -> str:
    """``text`` with every generated block made anew (an unknown block name, or a missing one, is an error)."""
    seen = set()

    def sub(m: re.Match[str]) -> str:
        name = m.group(2)
        if name not in BLOCKS:
            raise AssertionError(f"docs/protocol.md: unknown generated block {name!r}")
        seen.add(name)
        return f"{m.group(1)}{BLOCKS[name]()}\n{m.group(4)}"

    out = _BLOCK.sub(sub, text)
    if seen != set(BLOCKS):
        raise AssertionError(f"docs/protocol.md: generated blocks missing: {sorted(set(BLOCKS) - seen)}")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    text = DOC.read_text()
    new = render(text)
    if "--check" in argv:
        if new != text:
            print("docs/protocol.md is not current: python -m testbed.wire.spec", file=sys.stderr)
            return 1
        return 0
    DOC.write_text(new)
    return 0


if __name__ == "__main__":
    sys.exit(main())
