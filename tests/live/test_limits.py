"""Codebook limits, the recorder under 1e5 random messages, and two runs started in one second."""

from __future__ import annotations

import json
import os
import random
import subprocess
import textwrap

import numpy as np
import pytest
from helpers.cli import tb_run_here

from testbed import scenario
from testbed.loop.quantizer import MAX_CODES
from testbed.record import reader, recording
from testbed.sim.batch import simulate_batch, simulate_scenario, summarize
from testbed.wire import messages as msg
from testbed.wire import transport

BIG_M = 46340  # 46340^2 + 1 codes < 2^31 - 1: the largest M for n = 2


def _linear(n: int, M: int, extra: str = "") -> str:
    A = [[-1.0 if i == j else 0.0 for j in range(n)] for i in range(n)]
    B = [[1.0] for _ in range(n)]
    K = [[-0.1] * n]
    return textwrap.dedent(f"""
        name = "linear{n}"
        [plant]
        name = "linear"
        params = {{ A = {A}, B = {B} }}
        x0 = {[0.1] * n}
        [quantizer]
        T = 0.1
        M = {M}
        L = 1.0
        E0 = 0.2
        {extra}
        [controller]
        K = {K}
        [run]
        duration = 10.0
        """)


@pytest.mark.parametrize("n,M", [(25, 6), (2, 10**9), (2, BIG_M + 1)])
def test_a_codebook_beyond_the_limit_is_refused_up_front(tmp_path, n, M):
    f = tmp_path / "big.toml"
    f.write_text(_linear(n, M))
    r = tb_run_here("simulate", f)
    assert r.returncode == 2, r.stderr
    line = r.stderr.strip()
    assert len(line.splitlines()) == 1 and "[quantizer.M]" in line and "2^31 - 1" in line, line


@pytest.mark.slow  # half a second or more on a warm cache
def test_the_largest_codebook_works_end_to_end(tmp_path):
    """n = 2, M = 46340: 31-bit symbols, 4 bytes; simulate, the batch kernel, a recording and its report."""
    f = tmp_path / "big.toml"
    f.write_text(_linear(2, BIG_M))
    sc = scenario.load(f)
    assert BIG_M ** 2 + 1 <= MAX_CODES
    res = simulate_scenario(sc)
    s = summarize(sc, res)
    assert s["bits"] == 31 and s["converged"] and s["encoder_decoder_agree"]
    assert max(s["symbols"]) > 2**30  # codes from the top of the range travel too
    b = simulate_batch(sc.make_plant(), sc.K, sc.quantizer, sc.x0, sc.n_steps, record=True,
                       u_max=sc.controller.u_max)
    assert np.array_equal(b.x[0], res.x) and np.array_equal(b.E[0], res.E_enc)
    out = tmp_path / "big.mcap"
    recording.record_simulation(out, sc, res)
    r = tb_run_here("report", out, "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["symbols"] == s["symbols"] and rep["resimulation"]["reproduced"]


@pytest.mark.process
def test_the_largest_codebook_runs_live(tmp_path):
    from helpers.live import live_exact
    from helpers.procs import reap

    f = tmp_path / "big.toml"
    f.write_text(_linear(2, BIG_M))
    rid = f"t{os.getpid()}xbig"
    try:
        rc, s, err = live_exact(rid, str(f), "--duration", "2")
    finally:
        assert not reap(rid)
    assert rc == 0, (s["faults"], err[-2000:])
    sim = summarize(scenario.with_overrides(scenario.load(f), {"duration": 2.0}),
                    simulate_scenario(scenario.with_overrides(scenario.load(f), {"duration": 2.0})))
    assert s["symbols"] == sim["symbols"] and s["E"] == sim["E"] and s["x"] == sim["x"]
    assert s["sizes"]["symbol_payload_bytes"] == 4


# ============================================================================ the recorder, fuzzed
@pytest.mark.slow  # half a second or more on a warm cache
def test_the_recorder_survives_1e5_random_messages_in_bounded_memory(tmp_path):
    """Random keys, payloads and attachments (and mutations of genuine messages) straight into the
    recorder's decode-and-write path: no exception, every one counted, the file bounded and readable."""
    import zenoh

    from testbed.nodes.recorder import Recorder

    sc = scenario.load("paper")
    keys = transport.Keys.for_run("fuzz")
    path = tmp_path / "fuzz.mcap"
    w = recording.RecordingWriter(path, flush_interval=0.5)
    recording.write_text_metadata(w, sc, source="live", run_id="fuzz")
    rng = random.Random(1)
    pt = msg.PlantTelemetry(k=3, t_ns=1, sensor_tx_ns=1, u_rx_ns=1, delay_ns=0, theta=0, flags=0, flow_status=0,
                            x=(0.1, 0.1), u=(0.0,))
    et = msg.EncoderTelemetry(k=3, sensor_tx_ns=1, rx_ns=1, tx_ns=1, symbol=5, saturated=0, silent=0, E=0.1,
                              xi=(0.0, 0.0), q=(0.0, 0.0))
    good = {  # genuine messages to mutate: key -> (payload, attachment)
        "telemetry/plant": (msg.pack_batch([pt.encode()]), None),
        "telemetry/encoder": (msg.pack_batch([et.encode()]), None),
        "loop/sensor": msg.Sensor(3, 1, (0.1, 0.1)).encode(),
        "events/plant": (msg.Event(node="plant", kind="x", k=3).encode(), None),
        "control/start": (msg.Start(run_id="fuzz", t0_ns=1, T_ns=1, n_steps=30, digest="", timing="ideal",
                                    ack_via_attacker=False).encode(), None),
    }
    rels = list(good) + ["loop/symbol/rx", "loop/actuation", "loop/ack/tx", "summary/plant", "attacker/status",
                         "telemetry/nosuch", "nosuch", "telemetry/", ""]
    with zenoh.open(transport.make_config()) as session:
        rec = Recorder(session, keys, w, loop=True, n_steps=sc.n_steps)
        n = 100_000
        for i in range(n):
            rel = rng.choice(rels)
            payload, att = good.get(rel, (b"", None))
            payload = bytearray(payload or rng.randbytes(rng.randint(0, 64)))
            for _ in range(rng.randint(0, 4)):  # bit flips, cuts, extensions
                op = rng.random()
                if op < 0.5 and payload:
                    j = rng.randrange(len(payload))
                    payload[j] ^= 1 << rng.randrange(8)
                elif op < 0.75:
                    payload = payload[:rng.randint(0, len(payload))]
                else:
                    payload += rng.randbytes(rng.randint(1, 16))
            if rng.random() < 0.5:
                att = rng.randbytes(rng.choice([0, 5, 12, 12, 13]))
            rec._write(f"{keys.prefix}/{rel}", bytes(payload), att, 1_000 + i)
        st = rec.close()
    assert st["write_errors"] == 0, st
    assert st["malformed"] + st["written"] + st["rejected_k"] + st["warmup_skipped"] >= n * 0.9
    assert path.stat().st_size < 30e6  # malformed messages are recorded up to a bound, then only counted
    r = reader.read(path)
    assert not r.truncated and max(r.telemetry["plant"], default=0) < sc.n_steps
    assert len(r.malformed) <= Recorder.MAX_MALFORMED


# ============================================================================ two runs in one second
@pytest.mark.process
def test_two_runs_started_in_the_same_second_never_share_a_recording(tmp_path):
    from helpers.cli import tb_cmd
    from helpers.procs import reap

    env = dict(os.environ, TESTBED_RECORDINGS_DIR=str(tmp_path))
    rids = [f"t{os.getpid()}xtwin{i}" for i in range(2)]
    procs = [subprocess.Popen(tb_cmd("run", "paper", "--duration", "2", "--json", "--run-id", rid),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                              start_new_session=True) for rid in rids]
    try:
        outs = [p.communicate(timeout=300) for p in procs]
    finally:
        for rid in rids:
            reap(rid)
    paths = []
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err[-2000:]
        s = json.loads(out)
        assert s["recording"]["complete"]
        paths.append(s["recording"]["path"])
    assert len(set(paths)) == 2 and all(rid in p for rid, p in zip(rids, paths))
    for rid, pth in zip(rids, paths):
        r = reader.read(pth)
        assert r.start.run_id == rid and not r.truncated and len(r.telemetry["plant"]) == 20
    # an explicit --out that exists is refused, never overwritten
    r = subprocess.run(tb_cmd("run", "paper", "--duration", "1", "--out", paths[0]), capture_output=True, text=True,
                       timeout=120, env=env)
    assert r.returncode == 2 and "exists" in r.stderr and len(r.stderr.strip().splitlines()) == 1
