"""Fast unit tests of the live-run plumbing: messages, key expressions, Zenoh config, options."""

from __future__ import annotations

import argparse
import json
import math
import os
import threading
import time

import numpy as np
import pytest
from failclosed import require
from hypothesis import given, settings
from hypothesis import strategies as st

from testbed.wire import messages as msg
from testbed.wire import transport

i64 = st.integers(min_value=-(2**63), max_value=2**63 - 1)
u32 = st.integers(min_value=0, max_value=2**32 - 1)
fl = st.floats(allow_nan=False, width=64)
vec = st.lists(fl, min_size=1, max_size=6).map(tuple)


# ---------------------------------------------------------------- control path
@given(k=u32, stamp=i64)
def test_header_roundtrip_and_size(k, stamp):
    h = msg.Header(k, stamp)
    data = h.encode()
    assert len(data) == msg.HEADER_SIZE == 12
    assert msg.Header.decode(data) == h


@given(k=u32, stamp=i64, x=vec)
def test_sensor_roundtrip_bit_exact(k, stamp, x):
    p, a = msg.Sensor(k, stamp, x).encode()
    back = msg.Sensor.decode(p, a)
    assert back == msg.Sensor(k, stamp, x)
    assert len(p) == 8 * len(x)


@given(k=u32, stamp=i64, data=st.binary(min_size=0, max_size=8))
def test_symbol_payload_is_the_packed_bits(k, stamp, data):
    p, a = msg.Symbol(k, stamp, data).encode()
    assert p == data  # nothing but the symbol bits in the payload
    assert msg.Symbol.decode(p, a) == msg.Symbol(k, stamp, data)


def test_paper_symbol_is_one_byte():
    from testbed.loop.quantizer import Codebook

    cb = Codebook(2, 6, resilient=True)
    p, a = msg.Symbol(3, 0, cb.pack(36)).encode()
    assert len(p) == 1 and len(a) == msg.HEADER_SIZE


@given(k=u32, stamp=i64, theta=st.integers(0, 1), u=vec, last=st.integers(-1, 2**31 - 1))
def test_actuation_roundtrip(k, stamp, theta, u, last):
    m = msg.Actuation(k, stamp, theta, u, last)
    p, a = m.encode()
    assert len(p) == 5 + 8 * len(u)  # theta, last_rx (the ack it carries), u
    assert msg.Actuation.decode(p, a) == m
    assert m.ack() == msg.Ack(k, stamp, theta, last)


@given(k=u32, stamp=i64, theta=st.integers(0, 1), last=st.integers(-1, 2**31 - 1))
def test_ack_roundtrip(k, stamp, theta, last):
    m = msg.Ack(k, stamp, theta, last)
    p, a = m.encode()
    assert len(p) == 5
    assert msg.Ack.decode(p, a) == m


@pytest.mark.parametrize("payload,attachment", [
    (b"\x00" * 16, b"\x00" * 11),        # short header
    (b"\x00" * 16, None),                # no header at all
    (b"\x00" * 15, b"\x00" * 12),        # not whole float64s
    (b"", b"\x00" * 12),                 # empty state
    ("text", b"\x00" * 12),              # not bytes
])
def test_sensor_malformed(payload, attachment):
    with pytest.raises(msg.MessageError):
        msg.Sensor.decode(payload, attachment)


def test_actuation_and_ack_malformed():
    att = msg.Header(1, 2).encode()
    with pytest.raises(msg.MessageError):
        msg.Actuation.decode(b"\x00", att)
    with pytest.raises(msg.MessageError):
        msg.Actuation.decode(b"\x02" + b"\x00" * 8, att)  # theta = 2
    with pytest.raises(msg.MessageError):
        msg.Ack.decode(b"\x00" * 4, att)
    with pytest.raises(msg.MessageError):
        msg.Ack.decode(b"\x07" + b"\x00" * 4, att)
    assert issubclass(msg.MessageError, ValueError)


def test_warmup_index():
    assert msg.Header(msg.WARMUP_K, 0).warmup
    assert not msg.Header(0, 0).warmup


# ---------------------------------------------------------------- telemetry and JSON
def _tel_strategy(cls):
    fields = {
        msg.PlantTelemetry: dict(k=u32, t_ns=i64, sensor_tx_ns=i64, u_rx_ns=i64, delay_ns=i64,
                                 theta=st.integers(0, 255), flags=st.integers(0, 255),
                                 flow_status=st.integers(-128, 127), x=vec, u=st.lists(fl, max_size=3).map(tuple)),
        msg.EncoderTelemetry: dict(k=u32, sensor_tx_ns=i64, rx_ns=i64, tx_ns=i64,
                                   symbol=st.integers(-(2**31), 2**31 - 1), saturated=st.integers(0, 1),
                                   silent=st.integers(0, 1), E=fl, xi=vec, q=vec),
        msg.ControllerTelemetry: dict(k=u32, sym_stamp_ns=i64, rx_ns=i64, tx_ns=i64,
                                      symbol=st.integers(-(2**31), 2**31 - 1), theta=st.integers(0, 1),
                                      reason=st.integers(0, 3), E=fl, xi=vec, q=vec, u=vec),
        msg.AttackerTelemetry: dict(k=u32, rx_ns=i64, tx_ns=i64, dropped=st.integers(0, 1),
                                    corrupted=st.integers(0, 1), attack_on=st.integers(0, 1),
                                    dropped_total=u32, forwarded_total=u32),
    }[cls]
    return st.builds(cls, **fields)


@pytest.mark.parametrize("cls", list(msg.TELEMETRY_TYPES.values()))
@settings(max_examples=40)
@given(data=st.data())
def test_telemetry_roundtrip(cls, data):
    t = data.draw(_tel_strategy(cls))
    assert cls.decode(t.encode()) == t


@pytest.mark.parametrize("cls", list(msg.TELEMETRY_TYPES.values()))
def test_telemetry_truncated(cls):
    t = data_example(cls)
    raw = t.encode()
    for cut in (0, 3, len(raw) - 1):
        with pytest.raises(msg.MessageError):
            cls.decode(raw[:cut])
    with pytest.raises(msg.MessageError):
        cls.decode(raw + b"\x00")


def data_example(cls):
    return {
        msg.PlantTelemetry: msg.PlantTelemetry(1, 2, 3, 4, 5, 0, 0, 0, (0.1, 0.2), (0.3,)),
        msg.EncoderTelemetry: msg.EncoderTelemetry(1, 2, 3, 4, 5, 0, 0, 0.1, (0.0, 0.0), (0.1, 0.1)),
        msg.ControllerTelemetry: msg.ControllerTelemetry(1, 2, 3, 4, 5, 0, 0, 0.1, (0.0, 0.0), (0.1, 0.1), (1.0,)),
        msg.AttackerTelemetry: msg.AttackerTelemetry(1, 2, 3, 0, 0, 0, 4, 5),
    }[cls]


@given(recs=st.lists(st.binary(max_size=300), max_size=30))
def test_telemetry_batch_roundtrip(recs):
    assert msg.unpack_batch(msg.pack_batch(recs)) == recs


def test_telemetry_batch_truncated():
    raw = msg.pack_batch([b"abc", b"defg"])
    for cut in (1, 4, len(raw) - 1):
        with pytest.raises(msg.MessageError):
            msg.unpack_batch(raw[:cut])


@pytest.mark.parametrize("m", [
    msg.Start(run_id="r", t0_ns=123, T_ns=100_000_000, n_steps=50, digest="abc", timing="ideal",
              ack_via_attacker=False),
    msg.Stop(reason="done", origin="plant"),
    msg.Event(node="controller", kind="invalid_payload", k=5, t_ns=7, detail="bad"),
    msg.AttackerStatus(k=10, attack_on=True, dropped=1, forwarded=9),
    msg.NodeSummary(node="plant", data={"a": 1, "b": [1.5, None]}),
])
def test_json_messages_roundtrip(m):
    assert type(m).decode(m.encode()) == m


def test_json_messages_malformed():
    with pytest.raises(msg.MessageError):
        msg.Stop.decode(b"\xff\xfe")
    with pytest.raises(msg.MessageError):
        msg.Stop.decode(b"[1, 2]")
    with pytest.raises(msg.MessageError):
        msg.Event.decode(json.dumps({"node": "x", "nope": 1}).encode())


# ---------------------------------------------------------------- key expressions, config
def test_keys_one_prefix_per_run():
    k = transport.Keys.for_run("r1")
    names = [key for _, key in k.table()]
    assert all(key.startswith("testbed/r1/") for key in names)
    assert len(set(names)) == len(names)
    assert k.ack_for_encoder(False) == k.ack_tx and k.ack_for_encoder(True) == k.ack_rx
    assert transport.Keys.node_of(k.telemetry("plant")) == "plant"
    for bad in ("", "a/b", "a*", "x$"):
        with pytest.raises(ValueError):
            transport.Keys.for_run(bad)


def test_config_peer_loopback_no_multicast():
    conf = transport.make_config(listen=["tcp/127.0.0.1:7001"], connect=["tcp/127.0.0.1:7002"])
    assert json.loads(conf.get_json("mode")) == "peer"
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7001"]
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7002"]
    # no listen given: loopback only, never Zenoh's all-interfaces default
    conf = transport.make_config()
    assert json.loads(conf.get_json("listen/endpoints")) == [transport.LOOPBACK_ANY]


def test_config_file_is_read(tmp_path):
    f = tmp_path / "z.json5"
    f.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:7003"] }, '
                 'transport: { link: { tls: { root_ca_certificate: "/x/ca.pem" } } } }')
    conf = transport.make_config(config_file=f)
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7003"]
    assert json.loads(conf.get_json("transport/link/tls/root_ca_certificate")) == "/x/ca.pem"
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False


def test_free_port_and_endpoint_host():
    p = transport.free_port()
    assert 0 < p < 65536
    assert transport.endpoint_host("tcp/10.0.0.1:7447") == "10.0.0.1"
    assert transport.endpoint_host("tcp/[::1]:7447") == "::1"


# ---------------------------------------------------------------- run options and scenario overrides
def test_run_options_cli_roundtrip():
    from testbed.commands.liveconfig import run_options
    from testbed.nodes.options import RunOptions, add_run_option_arguments

    o = RunOptions(duration=5.0, T=0.05, timing="physical", deadline=0.4, mode="ideal", ack_via_attacker=True,
                   separate_ack=True, colocate=("encoder",))
    p = argparse.ArgumentParser()
    add_run_option_arguments(p)
    assert run_options(p.parse_args(o.cli())) == o
    assert RunOptions().cli() == []
    assert RunOptions().ack_on_actuation and not o.ack_on_actuation
    assert not RunOptions(separate_ack=True).ack_on_actuation
    assert o.processes == ("plant", "attacker", "controller") and o.process_of("encoder") == "plant"
    assert RunOptions().processes == transport.ROLES


def test_colocated_encoder_keys_move_to_the_plant():
    """--colocate encoder: the plant's user publishes the encoder's keys, the encoder's user nothing."""
    keys = transport.Keys.for_run("r")
    assert "loop/symbol/tx" not in transport.publish_keys("plant")
    co = ("encoder",)
    plant = transport.publish_keys("plant", co)
    assert {"loop/symbol/tx", "telemetry/encoder", "events/encoder", "summary/encoder", "alive/encoder",
            "ready/encoder", "loop/sensor", "telemetry/plant"} <= set(plant)
    assert transport.publish_keys("encoder", co) == []
    assert transport.publish_keys("attacker", co) == transport.publish_keys("attacker")
    acl = transport.acl_config(keys, co)
    rules = {r["id"]: r for r in acl["rules"]}
    assert "publish_encoder" not in rules
    assert "testbed/r/loop/symbol/tx" in rules["publish_plant"]["key_exprs"]
    plain = {r["id"]: r for r in transport.acl_config(keys)["rules"]}
    assert "testbed/r/loop/symbol/tx" not in plain["publish_plant"]["key_exprs"]
    (pol,) = [p for p in acl["policies"] if p["subjects"] == ["encoder"]]
    assert pol["rules"] == ["listen", "receive"]
    assert keys.ack_for_encoder(False, on_actuation=True) == keys.actuation
    assert keys.ack_for_encoder(False) == keys.ack_tx and keys.ack_for_encoder(True, True) == keys.ack_rx


def test_low_latency_config_and_router_without_scouting_delay():
    c = transport.make_config(mode="router", low_latency=True)
    assert json.loads(c.get_json("transport/unicast/lowlatency")) is True
    assert json.loads(c.get_json("transport/unicast/qos/enabled")) is False
    assert json.loads(c.get_json("scouting/delay")) == 0
    assert json.loads(transport.make_config(mode="peer").get_json("transport/unicast/lowlatency")) is False


def test_parse_cpus():
    from testbed.common.errors import BadInput
    from testbed.nodes.process import parse_cpus

    cpu = min(os.sched_getaffinity(0))
    assert parse_cpus(str(cpu)) == {cpu}
    assert parse_cpus(f"{cpu}-{cpu}") == {cpu}
    for bad in ("x", "", "999999", "1-"):
        with pytest.raises(BadInput):
            parse_cpus(bad)


def test_telemetry_is_published_off_the_callers_thread_in_order():
    import threading

    from testbed.nodes.context import TelemetryOut

    got, threads = [], []

    class Pub:
        def put(self, data):
            got.append(data)
            threads.append(threading.get_ident())

    t = TelemetryOut(Pub(), T_ns=1_000_000)  # 20 records a batch, published by its own thread
    recs = [bytes([i]) * 3 for i in range(45)]
    for r in recs:
        t.put(r)
    deadline = time.monotonic() + 5
    while len(got) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert len(got) == 2 and threading.get_ident() not in threads
    t.flush()  # the rest, from the caller
    assert [r for d in got for r in msg.unpack_batch(d)] == recs
    assert t.digest()["telemetry_records"] == 45
    slow = TelemetryOut(Pub(), T_ns=100_000_000)
    assert slow.n == 1 and slow.quiet_ns == 20_000_000  # at T = 0.1 s: 20 ms after the sample
    inline = TelemetryOut(Pub(), T_ns=100_000_000, background=False)
    n = len(got)
    inline.put(b"x")
    assert len(got) == n + 1 and threads[-1] == threading.get_ident()


def test_load_scenario_overrides_and_digest(paper):
    from testbed.nodes.options import RunOptions, T_ns, load_scenario, run_digest

    sc = load_scenario("paper", RunOptions(duration=5.0))
    assert sc.n_steps == 50 and sc.T == paper.T and np.array_equal(sc.K, paper.K)
    assert T_ns(sc) == 100_000_000
    sc2 = load_scenario("paper", RunOptions(duration=5.0, timing="physical", deadline=0.3))
    assert sc2.run.timing == "physical" and sc2.run.deadline == 0.3
    o = RunOptions(duration=5.0)
    assert run_digest(sc, o) != run_digest(sc2, o)
    assert run_digest(sc, o) != run_digest(sc, RunOptions(duration=5.0, ack_via_attacker=True))
    assert run_digest(sc, o) == run_digest(load_scenario("paper", o), o)


def test_load_scenario_T_override_is_validated():
    from testbed.common.errors import BadInput
    from testbed.nodes.options import RunOptions, load_scenario

    sc = load_scenario("pendulum", RunOptions(T=0.01, duration=1.0))  # LQR gain: recomputed for T
    assert sc.T == 0.01 and sc.n_steps == 100
    with pytest.raises(BadInput, match=r"T=0.2: .*M = 6 <= Lambda .*pass a larger M or a smaller T"):
        load_scenario("paper", RunOptions(T=0.2))  # Lambda = e^2 > M = 6: Assumption 2 broken
    with pytest.raises(BadInput, match="duration"):
        load_scenario("paper", RunOptions(duration=0.01))


def test_parse_corrupt():
    from testbed.nodes.attacker import parse_corrupt

    assert parse_corrupt("5,7:length, 9:range") == {5: "range", 7: "length", 9: "range"}
    assert parse_corrupt(None) == {}
    with pytest.raises(ValueError):
        parse_corrupt("3:zap")


def test_percentiles():
    from testbed.record.summary import percentiles

    p = percentiles([1000, 2000, 3000, msg.NO_TIME])
    assert p["n"] == 3 and p["p50"] == 2.0 and p["max"] == 3.0
    assert percentiles([])["p50"] is None


def test_run_clock_converts_realtime_to_monotonic():
    """now() is realtime - t0, bracketed by realtime reads (no fixed latency budget: a
    loaded machine may stall any line here); sleep_until never returns early."""
    import time

    from testbed.nodes.clock import RunClock

    t0 = time.time_ns() + 50_000_000
    c = RunClock(t0)
    before = time.time_ns() - t0
    now = c.now()
    after = time.time_ns() - t0
    slack = 200_000  # the realtime-monotonic offset is the best of 7 reads: ~1 us off when quiet
    assert before - slack <= now <= after + slack
    assert now < 0  # t0 is ahead
    t = c.sleep_until(-40_000_000, spin_ns=200_000)
    assert t >= -40_000_000 and c.now() >= t
    # a stop event ends a long sleep early, and says when
    stop = threading.Event()
    stop.set()
    assert c.sleep_until(10**12, stop=stop) < 10**12


# ---------------------------------------------------------------- lockstep helper of the encoder
def test_skip_sample_equals_a_lost_packet(paper):
    """An encoder that withheld sample k (skip_sample) stays in lockstep with a decoder that lost it."""
    from testbed.loop.flow import phi_T
    from testbed.nodes.encoder import skip_sample
    plant = paper.make_plant()
    enc = paper.make_method().make_encoder(plant, paper.K, paper.quantizer, paper.flow)
    dec = paper.make_method().make_decoder(plant, paper.K, paper.quantizer, paper.flow)
    x = paper.x0
    for k in range(6):
        if k in (2, 3):
            skip_sample(enc)
            u, _, _ = dec.step(None)
        else:
            i, _ = enc.encode(x)
            u, _, th = dec.step(i)
            enc.ack(th)
        assert np.array_equal(enc.xi, dec.xi) and enc.E == dec.E
        x, _ = phi_T(plant, x, u, paper.T, paper.flow)
    assert enc.saturations == 0
    assert math.isclose(enc.E, paper.quantizer.E0 * (paper.quantizer.Lambda / 6) ** 4 * paper.quantizer.Lambda ** 2)


def test_realtime_leaves_niced_background_threads_alone():
    """--realtime: SCHED_FIFO for the loop's threads, not for a niced logging thread (the Rerun tap)."""
    import os

    from testbed.nodes.process import set_realtime

    ready, done = threading.Event(), threading.Event()
    tid = {}

    def background():
        tid["bg"] = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid["bg"], 10)
        ready.set()
        done.wait(10)

    th = threading.Thread(target=background, daemon=True)
    th.start()
    ready.wait(10)
    try:
        if not set_realtime(True):
            require("fifo", "SCHED_FIFO not permitted here")
        assert os.sched_getscheduler(os.getpid()) == os.SCHED_FIFO
        assert os.sched_getscheduler(tid["bg"]) == os.SCHED_OTHER
    finally:
        set_realtime(False)
        done.set()
        th.join(10)
    assert os.sched_getscheduler(os.getpid()) == os.SCHED_OTHER
