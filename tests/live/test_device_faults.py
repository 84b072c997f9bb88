"""What a plant device does wrong is a fault on record (docs/live.md#a-device-that-misbehaves): a device that
sends a non-finite or wrong-length x_k, samples late by more than the deadline, never sends its Stop, or
disconnects for longer than Zenoh's lease, joined as ``testbed run paper --external plant`` (the bundled plant
with one fault: ``tests/data/nodes/faulty_device.py``).  Each is a fault with its kind and sample in the launcher's
summary and in the recording, one line on stderr and exit 1, within a bounded time."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import threading
from pathlib import Path

import pytest
from helpers.cli import PY, tb_cmd
from helpers.live import LOGS
from helpers.procs import reap

import testbed
from testbed.live.devicefaults import DEVICE_FAULTS, ENDS_RUN
from testbed.live.external import ANNOUNCE
from testbed.wire import join

DEVICE = str(Path(__file__).resolve().parents[1] / "data" / "nodes" / "faulty_device.py")


def test_every_device_fault_kind_is_documented():
    text = (Path(__file__).resolve().parents[2] / "docs" / "live.md").read_text()
    for kind in DEVICE_FAULTS:
        assert f"`{kind}`" in text, kind


def _run_with_device(run_id: str, out: Path, duration: float, *device_args: str):
    """``testbed run paper --external plant`` with ``faulty_device.py ARGS`` as the plant: (rc, summary, stderr);
    the test fails if the run does not end within 240 s of the join file (a hang)."""
    p = subprocess.Popen(tb_cmd("run", "paper", "--external", "plant", "--json", "--duration", str(duration),
                                "--out", str(out), "--run-id", run_id, "--run-dir", os.path.join(LOGS, run_id)),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    lines, seen = [], threading.Event()
    prefix = ANNOUNCE.format(role="plant", path="")

    def read_err():
        for line in p.stderr:
            lines.append(line)
            if line.startswith(prefix):
                seen.set()
        seen.set()

    out_text = []
    t = threading.Thread(target=read_err, daemon=True)
    t.start()
    t_out = threading.Thread(target=lambda: out_text.append(p.stdout.read()), daemon=True)
    t_out.start()
    dev = None
    try:
        assert seen.wait(120), "".join(lines)
        path = next(ln for ln in lines if ln.startswith(prefix))[len(prefix):].strip()
        with open(os.path.join(LOGS, f"{run_id}-device.log"), "wb") as log:
            dev = subprocess.Popen([PY, DEVICE, *device_args], stdout=log, stderr=subprocess.STDOUT,
                                   env={**os.environ, join.ENV: path}, start_new_session=True)
        p.wait(timeout=240)
    finally:
        for proc in (p, dev):  # the device that never stops, or froze, is ended here
            if proc is not None and proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        reap(run_id)
    t.join(10)
    t_out.join(10)
    return p.returncode, json.loads(out_text[0]), "".join(lines)


# (the device's fault, its sample K, the run's duration s) -> (the fault's kind, its sample)
CASES = {
    "nan-x": (("nan-x", "10"), 3, "state_nonfinite", 10),
    "short-x": (("short-x", "10"), 3, "state_wrong_length", 10),
    "late": (("late", "10"), 3, "sample_late", 10),
    "no-stop": (("no-stop",), 3, "no_stop", 30),
    # frozen at sample 10 (never wakes): its peers drop it once Zenoh's lease (10 s) runs out; the run is longer
    "disconnect": (("freeze", "10"), 15, "lost", None),
}


@pytest.mark.process
@pytest.mark.parametrize("case", list(CASES))
def test_a_device_fault_is_a_fault_on_record_one_line_and_exit_1(case, run_id, tmp_path):
    args, duration, kind, k = CASES[case]
    for attempt in range(3):  # a machine that stalls the device makes it late too: the first late sample counts
        rec = tmp_path / f"run{attempt}.mcap"
        rc, s, err = _run_with_device(run_id + "r" * attempt, rec, duration, *args)
        mine = [f for f in s["faults"] if f["node"] == "plant" and f["kind"] == kind]
        if not (kind == "sample_late" and mine and k is not None and mine[0]["at_sample"] < k):
            break
    assert rc == 1 and len(mine) == 1, (rc, s["faults"], err[-2000:])
    f = mine[0]
    # nothing else went wrong (but what a stalled machine does to a device: a stall, a late sample)
    assert all(x["kind"] in ("stalled", "sample_late") for x in s["faults"] if x is not f), s["faults"]
    if k is None:  # lost: the run's sample when the loss was seen; the device's own last sample before it
        assert 0 < f["last_sample_before"] < 10 <= f["at_sample"], f
    else:
        assert f["at_sample"] == k, f
    k = f["at_sample"]
    # one line on stderr, naming the kind and the sample
    said = [ln for ln in err.splitlines() if ln.startswith("testbed run: ") and f"sample {k}" in ln
            and (kind in ln or (kind == "lost" and "node plant lost at" in ln))]
    assert len(said) == 1, err[-2000:]
    # the run ends at a fault that ends it; a late sample is a deadline miss and the run goes on
    if kind in ENDS_RUN:
        assert s["outcome"] == f"plant {kind} at sample {k}", s["outcome"]
    else:
        assert s["outcome"] == "done" and s["samples"] == 30, (s["outcome"], s["samples"])
    # the recording is finalized, readable, and has the fault with its sample
    assert s["recording_complete"] is True, s["recording"]
    run = testbed.open(rec)
    on_record = [x for x in run.summary["faults"] if x["kind"] == kind]
    assert [(x["node"], x["at_sample"]) for x in on_record] == [("plant", k)], run.summary["faults"]
    from testbed.record.reader import read

    r = read(rec)
    assert [e.k for e in r.events if e.node == "launcher" and e.kind == f"plant_{kind}"] == [k], r.events
    if kind.startswith("state_"):  # the encoder's own event, at the sample it refused
        assert [e.k for e in r.events if e.node == "encoder" and e.kind == kind] == [k]
    plant_ks = sorted(r.telemetry.get("plant", {}))
    assert plant_ks == list(range(len(plant_ks))), plant_ks  # complete up to it
    assert plant_ks[-1] >= (f["last_sample_before"] if kind == "lost" else min(k, 29)), plant_ks
    if kind == "lost":
        assert plant_ks[-1] == f["last_sample_before"]


def test_every_device_fault_breaks_a_conformance_requirement():
    from testbed.live.conformance import DEVICE_FAULT_BREAKS, REQUIREMENTS

    assert set(DEVICE_FAULT_BREAKS) == set(DEVICE_FAULTS)
    assert set(DEVICE_FAULT_BREAKS.values()) <= set(REQUIREMENTS)


def test_the_encoder_names_what_is_wrong_with_an_x_k():
    from testbed.wire.messages import state_fault

    assert state_fault((1.0, -2.0), 2) is None
    assert state_fault((1.0, float("nan")), 2)[0] == "state_nonfinite"
    assert state_fault((float("-inf"), 0.0), 2)[0] == "state_nonfinite"
    assert state_fault((1.0,), 2) == ("state_wrong_length", "x has 1 entries, plant has n = 2")
    assert state_fault((1.0, 2.0, float("nan")), 2)[0] == "state_wrong_length"


@pytest.mark.process
def test_conformance_names_the_requirement_a_device_fault_breaks(tmp_path):
    cmd = tb_cmd("conformance", "plant", "paper", "--json", "--duration", "3", "--no-adverse", "--",
                 PY, DEVICE, "nan-x", "10")
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=tmp_path)
    try:
        res = json.loads(p.stdout)
    except json.JSONDecodeError:
        pytest.fail(f"no JSON (exit {p.returncode}): {p.stdout[-1000:]} {p.stderr[-2000:]}")
    q = {r["name"]: r for r in res["requirements"]}
    assert p.returncode == 1 and not res["passed"], res
    assert q["messages_well_formed"]["status"] == "fail", q["messages_well_formed"]
    assert q["messages_well_formed"]["detail"].startswith("device fault state_nonfinite at sample 10: "), q
