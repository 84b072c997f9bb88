"""docs/protocol.md and the code agree: the generated tables are current, and the worked example's
bytes, read back from the document, decode with the real decoders to the numbers of the simulator."""

from __future__ import annotations

import json
import math
import re
import struct
from pathlib import Path

import pytest

from testbed.wire import messages as msg
from testbed.wire import spec, transport

DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"


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


@pytest.mark.slow  # half a second or more on a warm cache
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


# ---------------------------------------------------------------- the flow map, the tables, the Zenoh configuration
def _terms(expr: str) -> list[tuple[float, int]]:
    """``0.5 * K0 - 0.25 * K3 + ...`` -> [(0.5, 0), (-0.25, 3), ...] (the sign folded into the literal)."""
    expr = expr.strip()
    out = []
    for sign, lit, j in re.findall(r"([+-]?)\s*(-?[0-9.e-]+) \* K(\d+)", expr):
        c = float(lit)
        out.append((-c if sign == "-" else c, int(j)))
    return out


def _doc_dop853():
    block = re.search(r"<!-- BEGIN generated:dop853 -->(.*?)<!-- END generated:dop853 -->", DOC.read_text(), re.S)
    stages = [_terms(e) for e in re.findall(r"y \+ h\*\((.*?)\); K\d+ = f", block.group(1))]
    e5 = _terms(re.search(r"err5 sum:\s+\((.*?)\) / sc", block.group(1)).group(1))
    e3 = _terms(re.search(r"err3 sum:\s+\((.*?)\) / sc", block.group(1)).group(1))
    return stages, e5, e3


def _lin(terms, K, i):
    acc = terms[0][0] * K[terms[0][1]][i]
    for c, j in terms[1:]:
        acc = acc + c * K[j][i]  # x + (-c) y is x - c y bit for bit
    return acc


def _phi_as_documented(f, x, u, T, rtol=1e-11, atol=1e-13, x_max=1e8, max_steps=20000):
    """The pseudo-code of docs/protocol.md (The flow map phi_T, bit for bit), in plain Python floats, with
    the coefficients read from the document."""
    stages, e5t, e3t = _doc_dop853()
    n = len(x)
    y = list(x)
    t, h, steps = 0.0, T, 0
    K = [None] * 13
    K[0] = f(y, u)
    while t < T:
        if steps >= max_steps:
            return y, 2
        last = t + h >= T
        if last:
            h = T - t
        for s, terms in enumerate(stages, 1):
            Y = [y[i] + h * _lin(terms, K, i) for i in range(n)]
            K[s] = f(Y, u)
        ynew = Y
        E5 = E3 = 0.0
        for i in range(n):
            sc = atol + rtol * max(abs(y[i]), abs(ynew[i]))
            a5, a3 = _lin(e5t, K, i) / sc, _lin(e3t, K, i) / sc
            E5 += a5 * a5
            E3 += a3 * a3
        den = (E5 + 0.01 * E3) * n
        err = 0.0 if den == 0.0 else abs(h) * E5 / math.sqrt(den)
        steps += 1
        if err <= 1.0:
            t = T if last else t + h
            y, K[0] = ynew, K[12]
            if not max(abs(v) for v in y) <= x_max:
                return y, 1
            if last:
                break
            h = h * (10.0 if err == 0.0 else min(10.0, 0.9 * err ** -0.125))
        else:
            h = h * (0.2 if err != err else max(0.2, 0.9 * err ** -0.125))
            if h < 1e-15 * T:
                return y, 2
    return y, 0


def test_the_documented_flow_map_reproduces_phi_T_bit_for_bit():
    """A node written from the document alone (the pseudo-code and the coefficient block, f as
    docs/plants-and-quantizer.md writes it) computes phi_T bit for bit, far points (many steps,
    rejections) included."""
    import numpy as np

    import plants
    from testbed.loop.flow import phi_T

    a, b = 1.0 / 3.0, 1.0 / 50.0

    def lienard(x, u):
        x1 = x[0]
        s = x1 * x1
        return [x[1] + x1 + a * x1 * s - b * x1 * s * s, -x1 + u[0]]

    rng = np.random.default_rng(7)
    X = np.vstack([[[0.1, 0.1]], rng.uniform(-0.5, 0.5, (6, 2)), rng.uniform(-4.0, 4.0, (4, 2))])
    U = np.vstack([[[0.0]], rng.uniform(-1.0, 1.0, (6, 1)), rng.uniform(-80.0, 80.0, (4, 1))])
    ref, st = phi_T(plants.make("lienard"), X, U, 0.1)
    for i in range(len(X)):
        y, s = _phi_as_documented(lienard, [float(v) for v in X[i]], [float(U[i, 0])], 0.1)
        assert s == int(st[i]) == 0
        assert y == [float(v) for v in ref[i]], (X[i], U[i])


def _table(block: str) -> list[list[str]]:
    text = re.search(rf"<!-- BEGIN generated:{block} -->(.*?)<!-- END generated:{block} -->", DOC.read_text(), re.S)
    rows = [r for r in text.group(1).strip().splitlines()[2:]]
    return [[c.strip() for c in r.strip("|").split("|")] for r in rows]


def test_the_flags_and_flow_status_tables_are_the_codes_the_plant_writes():
    from testbed.loop.flow import FLOW_DIVERGED, FLOW_OK, FLOW_STEP_LIMIT

    PT = msg.PlantTelemetry
    flags = {int(r[1]): r[2] for r in _table("flags")}
    assert set(flags) == {PT.FLAG_MISS, PT.FLAG_NO_U, PT.FLAG_CTRL_DEAD, PT.FLAG_FINAL} == {1, 2, 4, 8}
    assert flags[PT.FLAG_CTRL_DEAD].startswith("controller dead") and flags[PT.FLAG_FINAL].startswith("the final")
    codes = {int(r[0]): r[1].strip("`") for r in _table("flow_codes")}
    assert codes == {FLOW_OK: "ok", FLOW_DIVERGED: "diverged", FLOW_STEP_LIMIT: "step_limit"}
    text = DOC.read_text()
    assert "flags 6 (bit 1 u_k missing and\nbit 2 controller dead" in text and "`flags` 8\n(bit 3 alone)" in text


def test_telemetry_sha256_is_over_the_records_without_the_length_prefixes():
    """What the document says the digest covers, against the node's own TelemetryOut (on a real
    session) and the launcher's check of it."""
    import hashlib

    import zenoh

    from testbed.nodes.context import TelemetryOut

    recs = [msg.PlantTelemetry(k=k, t_ns=k, sensor_tx_ns=k, u_rx_ns=k, delay_ns=0, theta=0, flags=0, flow_status=0,
                               x=(0.5 * k, 1.0), u=(2.0,)).encode() for k in range(3)]
    conf = transport.make_config(listen=[f"tcp/127.0.0.1:{transport.free_port()}"])
    with zenoh.open(conf) as s:
        out = TelemetryOut(s.declare_publisher("testbed/spec/telemetry/plant"), 100_000_000, background=False)
        for r in recs:
            out.put(r)
        out.flush()
        d = out.digest()
    assert d["telemetry_records"] == 3
    assert d["telemetry_sha256"] == hashlib.sha256(b"".join(recs)).hexdigest()
    assert d["telemetry_sha256"] != hashlib.sha256(msg.pack_batch(recs)).hexdigest()
    assert "**not** the uint16 length prefixes" in DOC.read_text()


def _json5_blocks() -> list[dict]:
    return [json.loads(b) for b in re.findall(r"```json5\n(.*?)```", DOC.read_text(), re.S)]


def _leaves(d: dict, path=()):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _leaves(v, (*path, k))
        else:
            yield "/".join((*path, k)), v


def _get(conf, path: str):
    """A config value by path; Zenoh's get_json does not enter some maps (``connect/retry``): read the parent."""
    import zenoh

    try:
        return json.loads(conf.get_json(path))
    except zenoh.ZError:
        parent, _, leaf = path.rpartition("/")
        return _get(conf, parent)[leaf]


def test_the_documented_zenoh_configurations_are_what_the_sessions_set(tmp_path):
    """Every key of the json5 blocks of "Sessions, authentication and access rules", read from the config
    ``session_config`` builds for a node of each topology (DIR, ROLE, HOST:PORT, PASSWORD substituted)."""
    from testbed.wire.session import session_config

    peer, router_pw, router_tls, lowlat, acl = _json5_blocks()[:5]
    tls = transport.TlsCredentials.new(tmp_path / "tls")
    cred = transport.Credentials.new()
    secret = cred.write(tmp_path / "secret")
    keys = transport.Keys.for_run("RUN")
    ep = "127.0.0.1:7447"
    sub = {"DIR": str(tls.folder.resolve()), "ROLE": "encoder", "HOST:PORT": ep, "PASSWORD": cred.password("encoder")}

    def fill(v):
        if isinstance(v, str):
            for a, b in sub.items():
                v = v.replace(a, b)
        elif isinstance(v, list):
            v = [fill(e) for e in v]
        return v

    cases = [(peer, session_config("encoder", "peer", keys, connect=[f"tls/{ep}"], tls_dir=tls.folder)),
             (router_pw, session_config("encoder", "client", keys, connect=[f"tcp/{ep}"], secret_file=secret)),
             (router_tls, session_config("encoder", "client", keys, connect=[f"tls/{ep}"], tls_dir=tls.folder))]
    for doc, conf in cases:
        for path, v in _leaves(doc):
            assert _get(conf, path) == fill(v), path
    ll = session_config("encoder", "client", keys, connect=[f"tcp/{ep}"], secret_file=secret, low_latency=True)
    for path, v in _leaves(lowlat):
        assert _get(ll, path) == v, path
    def unset(v):  # Zenoh fills the fields nobody set with null
        if isinstance(v, dict):
            return {k: unset(e) for k, e in v.items() if e is not None}
        return [unset(e) for e in v] if isinstance(v, list) else v

    peer_acl = unset(_get(cases[0][1], "access_control"))
    assert peer_acl == acl["access_control"] == transport.acl_config(keys, by="cert_common_names")
    hub = session_config("plant", "router", keys, listen=[f"tcp/{ep}"], secret_file=secret, accepts=True)
    assert _get(hub, "mode") == "router" and _get(hub, "scouting/delay") == 0
    assert _get(hub, "transport/auth/usrpwd/dictionary_file") == str(secret.resolve())
    assert unset(_get(hub, "access_control")) == transport.acl_config(keys, by="usernames")
    assert "cert_common_names" in DOC.read_text()


def test_wait_ready_holds_bare_names():
    from testbed.wire import join

    (meaning,) = [m for name, _, m in join.FIELDS if name == "wait_ready"]
    assert "bare names, not keys" in meaning
    for name in (*transport.ROLES, transport.COLLECTOR):
        assert f'\\"{name}\\"' in meaning or f'"{name}"' in meaning
