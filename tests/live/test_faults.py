"""Fast checks of the fault handling: --stall's parsing, the stall watch on synthetic telemetry, the timing
criterion, the recorder's failing file, the node timing statistics in fixed memory."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from testbed.common.errors import BadInput
from testbed.live.stalls import StallWatch, parse_stalls
from testbed.record import recording
from testbed.record.degraded import timing_degraded
from testbed.record.timingstats import Timings, percentiles
from testbed.wire import messages as msg


def test_parse_stalls():
    assert parse_stalls(["plant@2:1.5", "controller@0:0.2"]) == {"plant": (2.0, 1.5), "controller": (0.0, 0.2)}
    for bad in ("plant@2", "plant:2@1", "x@1:1", "plant@-1:1", "plant@1:0", "plant@nan:1", "plant@1:inf"):
        with pytest.raises(BadInput, match="--stall must be"):
            parse_stalls([bad])
    with pytest.raises(BadInput, match="stall that one"):
        parse_stalls(["encoder@1:1"], colocated=("encoder",))


class FakeCollector:
    """The collector's queries over a dict of telemetry records (the stall watch reads nothing else)."""

    def __init__(self):
        self.d = {r: {} for r in ("plant", "encoder", "attacker", "controller")}

    def last_k(self, role):
        return max(self.d[role], default=-1)

    def record(self, role, k):
        return self.d[role].get(k)


def _plant(k, t_ns):
    return msg.PlantTelemetry(k=k, t_ns=t_ns, sensor_tx_ns=t_ns + 1000, u_rx_ns=msg.NO_TIME, delay_ns=0, theta=1,
                              flags=0, flow_status=0, x=(0.0, 0.0), u=(0.0,))


def _enc(k, sent, rx):
    return msg.EncoderTelemetry(k=k, sensor_tx_ns=sent, rx_ns=rx, tx_ns=rx + 100, symbol=0, saturated=0, silent=0,
                                E=1.0, xi=(0.0, 0.0), q=(0.0, 0.0))


def test_stall_watch_finds_a_frozen_plant_and_not_the_encoder_it_starved():
    """The plant frozen from 2.0 s to 3.5 s at T = 0.1 s (it then takes samples 21.. late, catching up):
    a stall of the plant from its last sample before (2.0 s) to its first after (3.5 s); the encoder,
    which got nothing meanwhile and handled each x_k at once, is no stall."""
    T = 100_000_000
    col, w = FakeCollector(), StallWatch(T, 100)
    t0 = 0
    for k in range(21):
        col.d["plant"][k] = _plant(k, k * T)
        col.d["encoder"][k] = _enc(k, k * T + 1000, k * T + 2000)
    assert w.tick(int(2.05e9), t0, col, {"plant", "encoder", "attacker", "controller"}) == []
    assert w.tick(int(2.6e9), t0, col, {"plant", "encoder", "attacker", "controller"}) == []
    assert "plant" in w.open and "encoder" not in w.open
    for k in range(21, 36):  # caught up at 3.5 s
        t = int(3.5e9) + (k - 21) * 1000
        col.d["plant"][k] = _plant(k, t)
        col.d["encoder"][k] = _enc(k, t + 1000, t + 2000)
    (fault,) = w.tick(int(3.6e9), t0, col, {"plant", "encoder", "attacker", "controller"})
    f = fault.to_dict()  # the summary's and the recording's form
    assert f["node"] == "plant" and f["kind"] == "stalled" and (f["from_s"], f["to_s"]) == (2.0, 3.5)
    assert f["last_sample_before"] == 20 and f["at_sample"] == 21 and not f["injected"]
    assert w.tick(int(3.7e9), t0, col, {"plant", "encoder", "attacker", "controller"}, final=True) == []


def test_stall_watch_ignores_a_launcher_that_saw_everything_late():
    """Telemetry that reached the launcher late (it was starved) but whose own stamps are on time: no stall."""
    T = 10_000_000
    col, w = FakeCollector(), StallWatch(T, 1000)
    for k in range(10):
        col.d["plant"][k] = _plant(k, k * T)
    w.tick(int(1e9), 0, col, {"plant"})  # 100 samples due, 10 seen: behind
    assert "plant" in w.open
    for k in range(10, 101):
        col.d["plant"][k] = _plant(k, k * T)
    assert w.tick(int(1.01e9), 0, col, {"plant"}) == [] and not w.open


def test_timing_degraded_criterion():
    clean = {"timing": {"deadline_misses": 0, "overruns": 0, "late_for_schedule": 0}, "events": {}, "faults": [],
             "late_symbols": 0, "loss_reasons": {"superseded": 0}, "node_summaries": {"encoder": {"stale_sensor": 0}}}
    assert timing_degraded(clean) == {"timing_degraded": False, "timing_degraded_why": None, "timing_faults": {}}
    s = json.loads(json.dumps(clean))
    s["timing"]["deadline_misses"] = 3
    s["faults"] = [{"node": "plant", "kind": "stalled", "from_s": 2.0, "to_s": 3.5}]
    d = timing_degraded(s)
    assert d["timing_degraded"] and d["timing_faults"] == {"deadline_misses": 3, "stalled": 1}
    assert d["timing_degraded_why"] == "deadline_misses 3, stalled 1 (plant 2.0-3.5 s)"
    s = json.loads(json.dumps(clean))
    s["events"] = {"ack_missing": 2}
    assert timing_degraded(s)["timing_degraded"]
    s["ack_via_attacker"] = True  # a missing ack is the attacker's doing there, not the host's
    assert not timing_degraded(s)["timing_degraded"]


def test_recording_writer_notices_its_file_removed(tmp_path):
    """A file removed under the writer (link count 0) fails at the next flush: one exception, PATH.error says
    why, later writes are dropped, and what was written before reads."""
    from testbed.record import reader

    path = tmp_path / "gone.mcap"
    w = recording.RecordingWriter(path, flush_interval=1e9, reserve=True)
    assert os.path.getsize(f"{path}.reserve") == recording.RESERVE_BYTES
    w.write("/recorder/malformed", {"key": "k", "payload": b"x", "attachment": b"", "error": "e"}, 1)
    w.flush()
    keep = tmp_path / "kept.mcap"
    os.link(path, keep)  # what was written, seen through a second name
    path.unlink()
    os.unlink(keep)
    with pytest.raises(recording.RecordingFailed, match="link count is 0"):
        w.flush()
    assert "link count is 0" in w.failed and not os.path.exists(f"{path}.reserve")
    assert json.loads(recording.error_path(path).read_text())["messages_written"] == 1
    w.write("/recorder/malformed", {"key": "k", "payload": b"x", "attachment": b"", "error": "e"}, 2)  # dropped
    w.close()
    # a file that stays: closed properly, no reserve left behind, and it reads
    ok = tmp_path / "ok.mcap"
    w = recording.RecordingWriter(ok, reserve=True)
    w.close()
    assert not os.path.exists(f"{ok}.reserve") and not reader.read(ok).truncated


def test_timings_in_fixed_memory_match_the_exact_percentiles():
    rng = np.random.default_rng(3)
    v = rng.integers(0, 10_000_000, size=5000)
    t = Timings(cap=8192)
    for x in v:
        t.append(int(x))
    t.append(msg.NO_TIME)  # never a value
    assert percentiles(t) == percentiles(v)  # below the cap: exact
    big = rng.lognormal(13, 1, size=200_000).astype(np.int64)
    t = Timings(cap=65536)
    for x in big:
        t.append(int(x))
    exact, est = percentiles(big), percentiles(t)
    assert est["n"] == exact["n"] == 200_000 and est["max"] == exact["max"]
    for q, p in (("p50", 0.50), ("p99", 0.99)):  # within 0.3 percentile points of the exact rank
        lo, hi = np.quantile(big, [p - 0.003, p + 0.003]) / 1e3
        assert lo <= est[q] <= hi, (q, est[q], exact[q])
    assert t.values().nbytes == 65536 * 8


def test_a_fault_line_has_one_sample_one_time_and_when_the_node_came_back():
    """``testbed run`` and ``testbed report`` print a fault with ``fault_line``: its sample and its time (a lost
    node's sample is the run's at its time, not the last sample the node had handled), and when it came back."""
    from testbed.record.faulttext import fault_line

    lost = {"node": "controller", "kind": "lost", "t_s": 10.9259, "at_sample": 109, "last_sample_before": 9,
            "why": "its peers dropped it", "back_s": 13.027}
    line = fault_line(lost)
    assert line == ("FAULT controller: lost (its peers dropped it) at sample 109 (10.9259 s); back at 13.027 s")
    assert "sample 9" not in line
    assert fault_line(dict(lost, back_s=None)).endswith("; not back by the end of the run")
    stalled = {"node": "plant", "kind": "stalled", "from_s": 1.0, "to_s": 2.1, "at_sample": 21, "why": "no samples"}
    assert fault_line(stalled) == "FAULT plant: stalled (no samples) at sample 21 (2.1 s)"
    cut = {"node": "controller", "kind": "link_cut", "t_s": 1.5, "down_s": 1.5, "up_s": 2.5, "why": "link down"}
    assert fault_line(cut) == "FAULT controller: link_cut (link down) at 1.5 s"
    killed = {"node": "encoder", "kind": "killed", "why": "killed by SIGKILL", "at_sample": 10, "t_s": 1.06,
              "last_log_line": "bye"}
    assert fault_line(killed) == "FAULT encoder: killed (killed by SIGKILL) at sample 10 (1.06 s); bye"
    assert fault_line({"node": None, "kind": "timeout", "why": "late"}) == "FAULT run: timeout (late)"


def test_liveliness_lost_means_a_token_that_went_during_the_fault():
    """A link cut's ``liveliness_lost``: the token went between the cut and its end (plus the grace), not
    at the run's end when every node closes its session (docs/live.md: a cut shorter than the lease does not
    end a session)."""
    import threading

    from testbed.live.stalls import lost_during

    class Liveliness:  # the collector's liveliness log: (monotonic ns, node, alive)
        lock = threading.Lock()
        liveliness = [(0, "controller", True), (9_000_000_000, "controller", False)]   # the run's end

    assert not lost_during(Liveliness, "controller", 1.5, 2.5, 0)
    Liveliness.liveliness = [(0, "controller", True), (2_200_000_000, "controller", False),
                             (2_700_000_000, "controller", True), (9_000_000_000, "controller", False)]
    assert lost_during(Liveliness, "controller", 1.5, 2.5, 0)
    assert not lost_during(Liveliness, "plant", 1.5, 2.5, 0)
    assert not lost_during(Liveliness, "controller", 1.5, 2.5, None)


def test_a_fault_is_written_one_way_and_read_back_as_written():
    """``Fault.to_dict`` writes exactly the keys a fault has (an unset field is absent, a None one is null);
    ``Fault.from_dict`` reads the written form back, keys it does not know included (an older or newer
    recording), so that reading and writing again changes nothing."""
    from testbed.record.faults import UNSET, Fault

    lost = Fault(role="controller", kind="lost", detail="gone", sample=12, time=1.2, last_sample_before=11,
                 injected=True)
    assert lost.to_dict() == {"node": "controller", "kind": "lost", "why": "gone", "at_sample": 12, "t_s": 1.2,
                              "injected": True, "last_sample_before": 11}
    lost.back_s = None  # not back by the end: written as null, not left out
    assert lost.to_dict()["back_s"] is None and lost.has_back
    run = Fault(role=None, kind="timeout", detail="late")
    assert run.to_dict() == {"node": None, "kind": "timeout", "why": "late"}
    for d in (lost.to_dict(), run.to_dict(), {"node": "plant", "kind": "new_kind", "why": "x", "future_key": [1]},
              {"kind": "old", "at_sample": 3}):
        assert Fault.from_dict(d).to_dict() == d
    assert Fault.from_dict({"kind": "old"}).sample is UNSET and Fault.from_dict({"kind": "k", "x": 1}).extra == {"x": 1}


def test_every_fault_site_writes_the_keys_of_its_kind():
    """The recorder's, the device watch's and a link cut's faults keep their written keys (the summary's
    ``faults`` entries are a user interface)."""
    import types

    from testbed.live.devicefaults import DeviceWatch
    from testbed.live.netns import NetnsRun
    from testbed.live.recorder import recorder_fault
    from testbed.record.faulttext import fault_line

    f, _ = recorder_fault(-9, {"t_s": 2.5, "signal": "SIGKILL"}, "a\nbye", True)
    assert f.to_dict() == {"node": "recorder", "kind": "killed", "why": "killed by SIGKILL", "t_s": 2.5,
                           "injected": True, "last_log_line": "bye"}
    assert fault_line(f) == fault_line(f.to_dict()) == "FAULT recorder: killed (killed by SIGKILL) at 2.5 s; bye"
    w = DeviceWatch(types.SimpleNamespace(T_ns=10_000_000, n_steps=10), 0.5, True)  # the plant's Start
    d = w._fault("sample_late", 4, 45_000_000, "late").to_dict()
    assert d == {"node": "plant", "kind": "sample_late", "why": "late", "at_sample": 4, "t_s": 0.045,
                 "external": True, "ends_run": False}
    cut = NetnsRun.__new__(NetnsRun)
    cut.cuts, cut.cut_state = [("controller", 1.0, 0.5)], {0: {"down_ns": 1_000_000_000}}
    cut._link = lambda role, state: None
    faults = []
    cut.tick(faults, None, 0)
    assert set(faults[0].to_dict()) == {"node", "kind", "why", "t_s", "injected", "down_s", "up_s"}
    assert faults[0].to_dict()["down_s"] == 1.0 and faults[0].to_dict()["up_s"] > 1.0
