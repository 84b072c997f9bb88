"""The quiet faults of a lab, with real processes: a frozen and resumed node (``--stall``), a full disk
under the recorder, an overloaded host."""

from __future__ import annotations

import contextlib
import io
import json

import pytest
from helpers.cli import run_cli, tb_cmd
from helpers.live import live

pytestmark = pytest.mark.process


def test_stalled_plant_encoder_and_controller_ride_through_and_resimulate(run_id, tmp_path):
    """Each of plant, encoder and controller frozen for 1 s mid-run (SIGSTOP, then SIGCONT): the run ends
    on time, each stall is recorded with its interval, encoder and decoder agree, resimulate reproduces."""
    out = tmp_path / "stalled.mcap"
    stalls = {"plant": 1.5, "encoder": 3.5, "controller": 5.5}
    args = [a for r, t in stalls.items() for a in ("--stall", f"{r}@{t}:1")]
    rc, s, err = live(run_id, "paper", "--duration", "8", "--out", str(out), *args)
    assert rc == 0, err[-2000:]
    assert s["outcome"] == "done" and s["complete"] and s["samples"] == 80
    got = {f["node"]: f for f in s["faults"] if f["kind"] == "stalled"}
    assert set(got) == set(stalls), s["faults"]
    assert all(f["kind"] == "stalled" for f in s["faults"]), s["faults"]
    for role, t in stalls.items():
        f = got[role]
        assert f["injected"]
        # from its last sample before the freeze (at most one period earlier) to its first after it
        assert t - 0.25 <= f["from_s"] <= t + 0.05 and 0.9 <= f["duration_s"] <= 1.6, f
        assert f"node {role} stalled" in err
    assert s["timing_degraded"] is True and "stalled" in s["timing_degraded_why"]
    assert s["encoder_decoder_agree_where_known"]
    # the samples a frozen node missed are losses at both ends: the controller decided them at its deadline
    assert s["loss_reasons"]["deadline"] >= 3 * 8
    rc, o, e = run_cli(tb_cmd("resimulate", str(out), "--json"))
    r = json.loads(o)
    assert rc == 0 and r["verdict"].startswith("reproduced") and r["first_divergence"] is None, (o, e[-2000:])
    rc, o, e = run_cli(tb_cmd("report", str(out), "--json"))
    rep = json.loads(o)
    assert rc == 0 and {f["node"] for f in rep["faults"] if f["kind"] == "stalled"} == set(stalls), rep["faults"]
    assert rep["timing_degraded"] is True


def test_stall_bad_input_is_one_line_exit_2(run_id):
    for bad in ("plant@2", "plant@x:1", "nobody@1:1", "plant@1:0"):
        rc, o, e = run_cli(tb_cmd("run", "paper", "--duration", "1", "--no-record", "--run-id", run_id,
                                  "--stall", bad), timeout=60)
        assert rc == 2 and "--stall must be ROLE@SECONDS:DURATION" in e and "Traceback" not in e, (bad, e)
    rc, o, e = run_cli(tb_cmd("run", "paper", "--duration", "1", "--no-record", "--run-id", run_id,
                              "--colocate", "encoder", "--stall", "encoder@0.5:1"), timeout=60)
    assert rc == 2 and "stall that one" in e and "Traceback" not in e, e


@pytest.fixture
def tiny_disk(tmp_path):
    """A 64 KiB tmpfs: a 10-second recording of the paper's run fills it after a few seconds."""
    import os
    import subprocess

    from failclosed import require

    d = tmp_path / "tiny"
    d.mkdir()
    if os.geteuid() != 0:
        require("mount", "mounting a tmpfs needs root")
    p = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(d)], capture_output=True, text=True)
    if p.returncode != 0:
        require("mount", f"mount -t tmpfs failed: {p.stderr.strip()}")
    yield d
    subprocess.run(["umount", "-l", str(d)], capture_output=True)


def test_recording_on_a_full_disk_says_so_and_stays_readable(run_id, tiny_disk):
    """The recorder's disk fills mid-run: one clear line, the run goes on (``continue``, the default) and
    reports its own outcome, the summary and the exit code (3) say the recording is incomplete, and the
    part written reads, with ``testbed report`` saying where it ends and why."""
    from testbed.live.recorder import RECORDING_INCOMPLETE

    out = tiny_disk / "full.mcap"
    rc, s, err = live(run_id, "paper", "--duration", "10", "--out", str(out))
    assert rc == RECORDING_INCOMPLETE, err[-2000:]
    assert s["outcome"] == "done" and s["complete"] and s["samples"] == 100
    assert s["recording_complete"] is False and not s["recording"]["complete"]
    (f,) = [f for f in s["faults"] if f["node"] == "recorder"]
    assert f["kind"] == "record_error" and "No space left on device" in f["why"], f
    lines = [x for x in err.splitlines() if "No space left on device" in x]
    assert len([x for x in lines if x.startswith("testbed run: the recording failed")]) == 1, err[-2000:]
    assert "Traceback" not in err
    rc, o, e = run_cli(tb_cmd("report", str(out), "--json", "--resimulate", "all"))
    assert rc == 0, e[-2000:]
    r = json.loads(o)
    assert r["recording"]["truncated"] and 10 <= r["samples"] < 100, (r["samples"], r["recording"])
    assert "No space left on device" in r["recording"]["ends"], r["recording"]
    assert r["resimulation"]["reproduced"], r["resimulation"]
    rc, o, e = run_cli(tb_cmd("report", str(out)))
    assert rc == 0 and "INCOMPLETE RECORDING: ends after" in o, o


def test_recording_removed_under_the_recorder_stops_the_run_when_asked(run_id, tmp_path):
    """The file removed mid-run (its link count drops to 0): found at the next flush; with
    ``--on-record-error stop`` the run ends there, and says why."""
    import subprocess
    import time

    from helpers.cli import PY, TIMEOUT

    out = tmp_path / "gone.mcap"
    # a run long enough that the removal is found (at the recorder's next flush, 0.5 s) long before its end,
    # however loaded the machine: the run stops there
    cmd = [PY, "-m", "testbed.cli", "run", "paper", "--duration", "60", "--json", "--run-id", run_id,
           "--out", str(out), "--on-record-error", "stop"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        end = time.monotonic() + TIMEOUT
        while time.monotonic() < end and p.poll() is None and (not out.exists() or out.stat().st_size < 20_000):
            time.sleep(0.05)
        out.unlink()
        o, e = p.communicate(timeout=TIMEOUT)
    finally:
        if p.poll() is None:
            p.kill()
    s = json.loads(o)
    assert p.returncode == 1 and s["outcome"] == "stopped: the recording failed", (p.returncode, s["outcome"], e[-2000:])
    (f,) = [f for f in s["faults"] if f["node"] == "recorder"]
    assert f["kind"] == "record_error" and "link count is 0" in f["why"], f
    assert s["recording_complete"] is False and s["samples"] < 600


def test_overloaded_host_reports_timing_degraded_and_resimulates(run_id, tmp_path):
    """A CPU hog on every core (at a higher priority where permitted) during a 3-second run at T = 5 ms:
    the timing summary counts the misses, the run says ``timing_degraded`` with the reason (summary and
    report alike), and what happened is still reproduced by ``testbed resimulate``."""
    import os
    import subprocess
    import sys

    out = tmp_path / "hog.mcap"
    hog = "import os, sys\ntry:\n    os.nice(-10)\nexcept OSError:\n    pass\nos.sched_setaffinity(0, {int(sys.argv[1])})\n" \
          "while True:\n    pass\n"
    hogs = [subprocess.Popen([sys.executable, "-c", hog, str(c)]) for c in sorted(os.sched_getaffinity(0))]
    try:
        # --realtime off: the loop at normal priority, as on a machine that does not permit SCHED_FIFO (at T = 5 ms
        # the default would put it above the hogs)
        rc, s, err = live(run_id, "paper", "--T", "0.005", "--duration", "3", "--out", str(out), "--realtime", "off")
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    assert rc in (0, 1), err[-2000:]  # a node may even be late for its own start; the run itself must end
    tm = s["timing"]
    assert tm["deadline_misses"] + tm["overruns"] > 0, tm
    assert s["timing_degraded"] is True and s["timing_degraded_why"], s.get("timing_degraded_why")
    assert s["timing_faults"].get("deadline_misses") == (tm["deadline_misses"] or None)
    rc, o, e = run_cli(tb_cmd("resimulate", str(out), "--json"))
    assert rc == 0 and json.loads(o)["first_divergence"] is None, (o[-2000:], e[-2000:])
    rc, o, e = run_cli(tb_cmd("report", str(out), "--json", "--resimulate", "0"))
    rep = json.loads(o)
    assert rep["timing_degraded"] is True, rep.get("timing_degraded_why")


def test_a_stall_longer_than_the_lease_is_a_peer_loss(run_id, tmp_path):
    """The controller frozen for 11.5 s, beyond Zenoh's 10-second lease: its peers drop it (fault ``lost``,
    exit 1), the plant runs on with u = 0 to the end, and the run is still re-simulated exactly."""
    out = tmp_path / "lease.mcap"
    rc, s, err = live(run_id, "paper", "--duration", "14", "--out", str(out), "--stall", "controller@1:11.5")
    assert rc == 1, err[-2000:]
    assert s["complete"] and s["samples"] == 140
    (f,) = [f for f in s["faults"] if f["kind"] == "lost"]
    assert f["node"] == "controller" and f["injected"] and 10.5 <= f["t_s"] <= 12.5, f
    assert "back_s" in f and (f["back_s"] is None or f["back_s"] >= 12.4), f  # its session back, if it came by the end
    assert 100 <= s["controller_lost_at"] <= 125
    # one sample and one time: the run's sample at t_s (the plant's controller_lost_at, give or take the one
    # sample between the two processes seeing the token go), not the last sample the frozen node handled
    assert f["at_sample"] == int(f["t_s"] / s["T"]) and abs(f["at_sample"] - s["controller_lost_at"]) <= 1, f
    assert f["last_sample_before"] <= 11, f
    assert f"node controller lost at sample {f['at_sample']} ({f['t_s']:g} s)" in err
    from testbed.commands.run import print_text

    with contextlib.redirect_stdout(io.StringIO()) as text:
        print_text(s)
    line = next(ln for ln in text.getvalue().splitlines() if "FAULT controller: lost" in ln)
    assert f"at sample {f['at_sample']} ({f['t_s']:g} s)" in line, line
    assert ("; back at" if f["back_s"] is not None else "; not back by the end of the run") in line, line
    rc, o, e = run_cli(tb_cmd("resimulate", str(out), "--json"))
    assert rc == 0 and json.loads(o)["first_divergence"] is None, (o[-2000:], e[-2000:])
