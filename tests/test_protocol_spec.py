"""docs/protocol.md and the code agree: the generated tables are current, and the worked example's
bytes, read back from the document, decode with the real decoders to the numbers of the simulator."""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path

import pytest

from testbed.wire import messages as msg
from testbed.wire import spec, transport

DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"


def test_the_protocol_document_is_current():
    text = DOC.read_text()
    assert spec.render(text) == text, "regenerate: python -m testbed.wire.spec"


def test_every_message_field_has_a_line_in_the_spec():
    spec._check_fields()  # raises on a field without a line, or a line without a field


def _example_from_doc() -> list[tuple[str, bytes, bytes]]:
    block = re.search(r"<!-- BEGIN generated:example -->(.*?)<!-- END generated:example -->", DOC.read_text(), re.S)
    code = re.search(r"```\n(.*?)```", block.group(1), re.S).group(1)
    out, cur, field = [], None, None
    for line in code.splitlines():
        if not line.strip():
            continue
        label, rest = line[:12].strip(), line[12:]
        if label == "key":
            cur = [rest.strip(), b"", b""]
            out.append(cur)
            continue
        field = {"attachment": 2, "payload": 1}.get(label, field)
        cur[field] += bytes.fromhex(rest.replace(" ", ""))
    return [tuple(m) for m in out]


def test_the_worked_example_decodes_to_the_simulators_numbers():
    """Parse the hex dump of docs/protocol.md and decode it with the real decoders; the numbers must be
    those of sample 0 of ``testbed simulate paper`` (an independent run of the per-sample simulator)."""
    import numpy as np

    from testbed import scenario
    from testbed.sim.batch import simulate_scenario

    msgs = {k.split("/", 2)[2]: (p, a) for k, p, a in _example_from_doc()}
    assert set(msgs) == {"loop/sensor", "loop/symbol/tx", "loop/symbol/rx", "loop/actuation", "telemetry/plant",
                         "telemetry/encoder", "telemetry/attacker", "telemetry/controller"}
    sc = scenario.load("paper")
    res = simulate_scenario(sc, n_steps=1)
    s = msg.Sensor.decode(*msgs["loop/sensor"])
    assert s.k == 0 and s.x == tuple(sc.x0)
    sym = msg.Symbol.decode(*msgs["loop/symbol/tx"])
    assert msgs["loop/symbol/rx"] == msgs["loop/symbol/tx"]  # the attacker forwards payload and header unchanged
    a = msg.Actuation.decode(*msgs["loop/actuation"])
    assert (a.k, a.theta, a.last_rx) == (0, 0, 0)
    assert np.array_equal(np.asarray(a.u), np.asarray(res.u)[0])  # bit for bit
    assert int.from_bytes(sym.data, "big") == int(np.asarray(res.symbols)[0])
    (enc_rec,) = msg.unpack_batch(msgs["telemetry/encoder"][0])
    e = msg.EncoderTelemetry.decode(enc_rec)
    assert e.E == float(res.E_enc[0]) and e.q == tuple(res.q_enc[0]) and e.symbol == int.from_bytes(sym.data, "big")
    (ctl_rec,) = msg.unpack_batch(msgs["telemetry/controller"][0])
    c = msg.ControllerTelemetry.decode(ctl_rec)
    assert c.u == a.u and c.theta == int(res.theta[0]) == 0 and c.E == float(res.E_dec[0])
    (pl_rec,) = msg.unpack_batch(msgs["telemetry/plant"][0])
    p = msg.PlantTelemetry.decode(pl_rec)
    assert p.x == s.x == tuple(res.x[0]) and p.u == a.u
    (at_rec,) = msg.unpack_batch(msgs["telemetry/attacker"][0])
    assert msg.AttackerTelemetry.decode(at_rec).dropped == 0


def test_the_header_layout_is_what_the_spec_says():
    """An independent reading of the documented header: k uint32 LE at 0, stamp int64 LE at 4."""
    raw = msg.Header(0x01020304, -5).encode()
    assert len(raw) == 12 == msg.HEADER_SIZE
    assert raw[:4] == bytes([4, 3, 2, 1]) and struct.unpack("<q", raw[4:]) == (-5,)
    act, _ = msg.Actuation(7, 0, 1, (1.5,), 6).encode()
    assert act == b"\x01" + (6).to_bytes(4, "little", signed=True) + struct.pack("<d", 1.5)


def test_every_publishable_key_is_in_the_spec_and_every_spec_key_exists():
    keys = transport.Keys.for_run("r")
    rels = {k.split("/", 2)[2] for _, k in keys.table()}
    generic = {spec._generic(k) for k in rels}
    assert generic - {"<node>"} <= set(spec.KEY_DOC), generic - set(spec.KEY_DOC)
    for key in spec.KEY_DOC:
        assert spec._publishers(key), key
    text = DOC.read_text()
    for key in spec.KEY_DOC:
        assert f"`{key}`" in text


def test_start_carries_the_protocol_version_and_decode_checks_it_first():
    st = msg.Start(run_id="r", t0_ns=1, T_ns=2, n_steps=3, digest="d", timing="ideal", ack_via_attacker=False)
    d = json.loads(st.encode())
    assert d["protocol"] == msg.PROTOCOL_VERSION
    assert msg.Start.decode(st.encode()) == st
    for theirs, shown in ((msg.PROTOCOL_VERSION + 1, str(msg.PROTOCOL_VERSION + 1)), ("1", "'1'"), (True, "True")):
        bad = dict(d, protocol=theirs, t0_ns="not even a number")  # the version is checked before anything else
        with pytest.raises(msg.ProtocolMismatch) as e:
            msg.Start.decode(json.dumps(bad).encode())
        assert str(e.value) == f"the run speaks protocol version {shown}, this node speaks {msg.PROTOCOL_VERSION}"
    d.pop("protocol")
    with pytest.raises(msg.ProtocolMismatch) as e:
        msg.Start.decode(json.dumps(d).encode())
    assert e.value.theirs == 0
    assert f"Protocol version: **{msg.PROTOCOL_VERSION}**" in DOC.read_text()


def test_a_client_joins_the_router_topology_over_mutual_tls_and_the_router_checks_it(tmp_path):
    """The authenticated way in for a device that has mutual TLS but no user/password (zenoh-pico):
    nodes started by hand in the router topology with --tls-dir.  Real Zenoh sessions: the plant's (the
    router, by ``zenoh_config``), the controller's (a client, likewise), and a bare Zenoh client with the
    encoder's certificate and nothing else, as a device would present.  The device's symbol reaches the
    controller; its forged actuation does not; a certificate of another authority gets no session."""
    import threading
    import time

    import zenoh

    from testbed.wire.session import SessionOptions, security_info, zenoh_config

    tls = transport.TlsCredentials.new(tmp_path / "tls")
    keys = transport.Keys.for_run("tlsrouter")
    ep = f"tls/127.0.0.1:{transport.free_port()}"

    def args(**kw):
        return SessionOptions(**{"topology": "router", "tls_dir": str(tls.folder), **kw})

    assert security_info(args())["transport"] == "mutual tls"
    device_conf = transport.make_config(connect=[ep], mode="client", tls=tls.zenoh("encoder"))
    got, lock = [], threading.Lock()

    def on(sample):
        with lock:
            got.append((str(sample.key_expr), sample.payload.to_bytes()))

    with zenoh.open(zenoh_config(args(listen=(ep,)), "plant", keys, hub=True)) as plant, \
            zenoh.open(zenoh_config(args(connect=(ep,)), "controller", keys)) as ctl, \
            zenoh.open(device_conf) as device:
        assert plant is not None
        subs = [ctl.declare_subscriber(keys.symbol_tx, on), ctl.declare_subscriber(keys.actuation, on)]
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            device.put(keys.symbol_tx, b"\x23")   # the encoder's own key
            device.put(keys.actuation, b"forged")  # the controller's key: the router refuses it
            with lock:
                if (keys.symbol_tx, b"\x23") in got:
                    break
            time.sleep(0.1)
        time.sleep(0.5)
        for s in subs:
            s.undeclare()
    assert (keys.symbol_tx, b"\x23") in got
    assert not [g for g in got if g[0] == keys.actuation]
    other = transport.TlsCredentials.new(tmp_path / "other")
    with zenoh.open(zenoh_config(args(listen=(ep,)), "plant", keys, hub=True)):
        stranger = transport.make_config(connect=[ep], mode="client", tls=other.zenoh("encoder"))
        stranger.insert_json5("connect/timeout_ms", "2000")
        with pytest.raises(zenoh.ZError):
            zenoh.open(stranger)
