"""Soak benchmark: long live runs, and every process's memory, open files and threads over time.

Runs ``testbed run paper --T T --duration S`` (the paper's plant and gain, recorded) for each
length of ``--durations`` (or one of ``--minutes``) and every ``--every`` seconds prints, for the
launcher and each of its child processes (the nodes ``tb-plant``, ``tb-encoder``, ``tb-attacker``,
``tb-controller`` and the recorder), the resident memory (VmRSS), its peak so far (VmHWM), the
open file descriptors and the threads, read from ``/proc``.  At the end of each run it prints each
process's memory growth after the warm-up (``--warmup`` s: a least-squares slope of RSS over time,
in MB per hour) against the goal (less than 5 MB an hour) and its peak (VmHWM; the launcher's also as it
reports it in its summary, ``launcher.peak_rss_mb``, and at its exit, ``wait4``'s ``ru_maxrss``, so the
end of the run and the printing of its summary are included; each run is started by a fresh process of this
script, whose own memory ``ru_maxrss`` would otherwise count), and the
recording's completeness: ``recording_complete`` from the run's summary and the samples
``testbed report`` reads back against the run's samples.  With several durations it then prints
the launcher's peak against the run's length, as a ratio to its peak in the shortest run (the goal:
flat, within 25 %).  ``--synthetic N,N,...`` runs no live run: it writes spills of N samples of the
four nodes' telemetry with the collector's writer and builds the launcher's end-of-run summary from
each in-process as the launcher builds it (``synthetic_summary_peak``: rows of the spill a chunk at a
time, ``build_summary``, the ``--json`` output to a sink), printing its peak memory (tracemalloc) against N.
``--starve-recorder ON,OFF`` stops and continues the recorder (SIGSTOP, SIGCONT) in a cycle of ON ms running
and OFF ms stopped while the loop runs, as a recorder at nice 10 on a loaded machine gets little CPU: its
writer falls behind and its queue grows (what its memory then does is the figure to read).  ``--mcap-index
HOURS`` runs no live run either: it drives mcap's ``Writer`` as the recorder does (a chunk closed every 0.5 s,
9 channels) and prints the memory it keeps for the file's summary section, which grows with the run.

    python benchmarks/bench_soak.py --minutes 10                       # T = 10 ms for 10 minutes
    python benchmarks/bench_soak.py --minutes 60 --every 60 --json soak.json
    python benchmarks/bench_soak.py --rate 1000 --durations 60,180     # 1 kHz, 1 and 3 minutes
    python benchmarks/bench_soak.py --synthetic 200000,1200000         # the end of run alone, in-process
    python benchmarks/bench_soak.py --rate 1000 --durations 150 --starve-recorder 5,45   # a writer behind
    python benchmarks/bench_soak.py --mcap-index 1                     # the recorder's MCAP index, an hour
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

#: memory growth per hour after warm-up that counts as flat (the goal of docs/benchmarks.md)
GOAL_MB_PER_H = 5.0
#: the launcher's peak in a longer run against the shortest's that counts as flat
GOAL_PEAK_RATIO = 1.25
#: readings later than the run's length plus this (start-up) are after the loop: left out of the growth
STARTUP_S = 5.0
#: seconds between two readings once the loop is over (the end of the run, whose peak is measured)
END_EVERY = 0.05


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def proc_info(pid: int) -> dict | None:
    """RSS and peak RSS (MB), open files and threads of one process, from /proc; None when it is gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
        comm = Path(f"/proc/{pid}/comm").read_text().strip()
    except OSError:
        return None
    f = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    if "VmRSS" not in f:  # a zombie: exited, not yet reaped
        return None
    return {"name": comm, "rss_mb": int(f["VmRSS"].split()[0]) / 1024, "hwm_mb": int(f["VmHWM"].split()[0]) / 1024,
            "fds": fds, "threads": int(f["Threads"])}


def children(pid: int) -> list[int]:
    """The direct children of ``pid`` (the launcher's nodes and recorder, in sessions of their own)."""
    out = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            stat = Path(f"/proc/{d}/stat").read_text()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            out.append(int(d))
    return sorted(out)


def slope_per_hour(ts: list[float], ys: list[float]) -> float | None:
    """Least-squares slope of ys over ts (seconds), per hour; None with fewer than 3 points."""
    if len(ts) < 3:
        return None
    n = len(ts)
    mt, my = sum(ts) / n, sum(ys) / n
    var = sum((t - mt) ** 2 for t in ts)
    if var == 0:
        return None
    return sum((t - mt) * (y - my) for t, y in zip(ts, ys)) / var * 3600


def starve(launcher: int, seconds: float, on_s: float, off_s: float, done: threading.Event) -> None:
    """SIGSTOP and SIGCONT the launcher's recorder in a cycle (``on_s`` running, ``off_s`` stopped) for ``seconds``
    from when it appears, or until ``done``."""
    rec = None
    while rec is None and not done.is_set():
        rec = next((c for c in children(launcher) if " record " in cmdline(c)), None)
        done.wait(0.05)
    if rec is None:
        return
    end = time.monotonic() + seconds
    try:
        while not done.is_set() and time.monotonic() < end:
            os.kill(rec, signal.SIGSTOP)
            done.wait(off_s)
            os.kill(rec, signal.SIGCONT)
            done.wait(on_s)
    except ProcessLookupError:
        return
    finally:
        try:
            os.kill(rec, signal.SIGCONT)
        except ProcessLookupError:
            pass


def reaped_peak_mb(p: subprocess.Popen) -> float | None:
    """``p.poll()`` that reaps the launcher itself: None while it runs, else its peak RSS over its whole life
    (``wait4``'s ``ru_maxrss``: the largest of the launcher and the children it reaped, the launcher being the
    largest), its exit code set on ``p``."""
    pid, status, ru = os.wait4(p.pid, os.WNOHANG)
    if pid == 0:
        return None
    p.returncode = os.waitstatus_to_exitcode(status)
    return ru.ru_maxrss / 1024


def soak(dur: float, a, every: float, warmup: float) -> dict | None:
    """One run of ``dur`` seconds: its readings, each process's growth and peak, the recording's completeness."""
    tmp = tempfile.mkdtemp(prefix="bench-soak-")
    out = a.out or os.path.join(tmp, "soak.mcap")
    cmd = [sys.executable, "-m", "testbed.cli", "run", "paper", "--T", str(a.T), "--duration", f"{dur:g}",
           "--json", "--out", out, "--force"]
    print(f"\nbench_soak: {' '.join(cmd[2:])}", flush=True)
    so_path, se_path = Path(tmp) / "summary.json", Path(tmp) / "stderr.txt"
    with open(so_path, "w") as so_f, open(se_path, "w") as se_f:  # a pipe would fill with the summary and block it
        p = subprocess.Popen(cmd, stdout=so_f, stderr=se_f, text=True, start_new_session=True)
    t_start = time.monotonic()
    starved = threading.Event()
    if a.starve_recorder:
        on_ms, off_ms = a.starve_recorder
        print(f"bench_soak: the recorder starved while the loop runs: {on_ms:g} ms running, {off_ms:g} ms stopped",
              flush=True)
        threading.Thread(target=starve, args=(p.pid, dur + STARTUP_S, on_ms / 1e3, off_ms / 1e3, starved),
                         daemon=True).start()
    readings: list[dict] = []
    peak: dict[str, float] = {}
    next_print = 0.0
    try:
        print(f"{'t [s]':>7}  {'process':>13} {'RSS MB':>7} {'peak MB':>8} {'fds':>4} {'thr':>4}")
        while (exit_peak := reaped_peak_mb(p)) is None:
            t = time.monotonic() - t_start
            over = t > dur + STARTUP_S
            time.sleep(END_EVERY if over else (every if readings else min(every, 5.0)))
            t = time.monotonic() - t_start
            procs = {p.pid: proc_info(p.pid), **{c: proc_info(c) for c in children(p.pid)}}
            row = {"t_s": round(t, 1), "procs": {}, "running": t <= dur + STARTUP_S}
            show = t >= next_print
            for pid, info in procs.items():
                if info is None:
                    continue
                name = "launcher" if pid == p.pid else info["name"]
                if pid != p.pid and not name.startswith("tb-"):
                    name = "recorder" if " record " in cmdline(pid) else name
                row["procs"][name] = info
                peak[name] = max(peak.get(name, 0.0), info["hwm_mb"])
                if show:
                    print(f"{t:7.0f}  {name:>13} {info['rss_mb']:7.1f} {info['hwm_mb']:8.1f} {info['fds']:4d} "
                          f"{info['threads']:4d}", flush=True)
            if show:
                next_print = t + every - 0.5
            readings.append(row)  # every one after the loop too: the end of the run
        p.wait()
    except KeyboardInterrupt:
        starved.set()
        os.killpg(p.pid, signal.SIGINT)
        p.wait()
        raise
    finally:
        starved.set()
    so, se = so_path.read_text(), se_path.read_text()
    try:
        summary = json.loads(so)
    except ValueError:
        print(f"bench_soak: the run printed no summary (exit {p.returncode}): {se[-1000:]}", file=sys.stderr)
        return None
    reported = (summary.get("launcher") or {}).get("peak_rss_mb")
    sources = {"polled": peak.get("launcher"), "reported": reported, "at_exit": exit_peak}
    if reported is not None:  # the launcher's own VmHWM, read after its summary (the last poll may be earlier)
        peak["launcher"] = max(peak.get("launcher", 0.0), reported)
    if exit_peak:  # ... and at its exit: printing the --json summary included
        peak["launcher"] = max(peak.get("launcher", 0.0), exit_peak)
    print("the launcher's peak: " + ", ".join(f"{k} {v:.1f} MB" for k, v in sources.items() if v is not None)
          + " (polled VmHWM; its own launcher.peak_rss_mb; wait4's ru_maxrss)")
    figures = {}
    print(f"memory growth after {warmup:g} s of warm-up (goal < {GOAL_MB_PER_H:g} MB/h) and peak (VmHWM):")
    names = sorted({n for r in readings for n in r["procs"]})
    for name in names:
        pts = [(r["t_s"], r["procs"][name]) for r in readings
               if name in r["procs"] and r["t_s"] >= warmup and r["running"]]
        g = slope_per_hour([t for t, _ in pts], [i["rss_mb"] for _, i in pts])
        first = pts[0][1] if pts else None
        last = pts[-1][1] if pts else None
        figures[name] = {"mb_per_hour": g, "rss_first_mb": first and first["rss_mb"], "rss_last_mb": last and last["rss_mb"],
                         "peak_mb": peak.get(name),
                         "fds_first": first and first["fds"], "fds_last": last and last["fds"],
                         "threads_first": first and first["threads"], "threads_last": last and last["threads"],
                         "flat": None if g is None else g < GOAL_MB_PER_H}
        print(f"  {name:>13}: " + ("too few readings" if g is None else
                                   f"{g:+8.2f} MB/h ({first['rss_mb']:.1f} -> {last['rss_mb']:.1f} MB; fds "
                                   f"{first['fds']} -> {last['fds']}, threads {first['threads']} -> {last['threads']})"
                                   f" {'ok' if g < GOAL_MB_PER_H else 'OVER THE GOAL'}")
              + f"; peak {peak.get(name, float('nan')):.1f} MB")
    rep = subprocess.run([sys.executable, "-m", "testbed.cli", "report", out, "--json", "--resimulate", "0"],
                         capture_output=True, text=True)
    try:
        rec_samples = json.loads(rep.stdout)["samples"]
    except (ValueError, KeyError):
        rec_samples = None
    rec = {"recording_complete": summary.get("recording_complete"), "run_samples": summary.get("samples"),
           "n_steps": summary.get("n_steps"), "recorded_samples": rec_samples, "exit_code": p.returncode,
           "outcome": summary.get("outcome"), "deadline_misses": summary.get("timing", {}).get("deadline_misses"),
           "timing_degraded": summary.get("timing_degraded"),
           "faults": sorted({f"{f.get('node') or 'run'}: {f.get('kind')}" for f in summary.get("faults") or ()}),
           "summary_bytes": len(so), "telemetry_lag": (summary.get("launcher") or {}).get("telemetry_lag"),
           "telemetry_lag_of": (summary.get("launcher") or {}).get("telemetry_lag_of")}
    print(f"run: {rec['outcome']}, exit {rec['exit_code']}, {rec['run_samples']}/{rec['n_steps']} samples, "
          f"{rec['deadline_misses']} deadline misses, timing degraded: {rec['timing_degraded']}")
    print(f"recording: complete {rec['recording_complete']}, {rec_samples} samples read back by testbed report")
    print(f"summary: {rec['summary_bytes']} bytes of --json; records out of order by {rec['telemetry_lag']} samples "
          f"(by node: {rec['telemetry_lag_of']})")
    if rec["faults"]:
        print(f"faults: {', '.join(rec['faults'])}")
    if not a.out:
        Path(out).unlink(missing_ok=True)
        Path(out + ".reserve").unlink(missing_ok=True)  # the recorder's disk reserve, left by one it could not finish
    for f in (so_path, se_path):
        f.unlink(missing_ok=True)
    if not os.listdir(tmp):
        os.rmdir(tmp)
    return {"duration_s": dur, "T": a.T, "warmup_s": warmup, "readings": readings, "growth": figures,
            "peak_mb": peak, "launcher_peak_sources": sources, "recording": rec}


def synthetic_spill(path, sc, n: int) -> None:
    """``n`` samples of the four nodes' telemetry (and the plant's final record) written with the collector's
    own writer (``testbed.live.collect.Spill``) as a run at ``sc.T`` would leave them, times jittered."""
    import numpy as np

    from testbed.live.collect import Spill
    from testbed.wire import messages as msg

    Tn = int(round(sc.T * 1e9))
    recs = [msg.PlantTelemetry(k=0, t_ns=0, sensor_tx_ns=0, u_rx_ns=0, delay_ns=0, theta=0, flags=0, flow_status=0,
                               x=(0.1, 0.1), u=(0.2,)),
            msg.EncoderTelemetry(k=0, sensor_tx_ns=0, rx_ns=0, tx_ns=0, symbol=5, saturated=0, silent=0, E=0.1,
                                 xi=(0.1, 0.1), q=(0.1, 0.1)),
            msg.AttackerTelemetry(k=0, rx_ns=0, tx_ns=0, dropped=0, corrupted=0, attack_on=0, dropped_total=0,
                                  forwarded_total=0),
            msg.ControllerTelemetry(k=0, sym_stamp_ns=0, rx_ns=0, tx_ns=0, symbol=5, theta=0, reason=0, E=0.1,
                                    xi=(0.1, 0.1), q=(0.1, 0.1), u=(0.2,))]
    # the byte offsets of k and of each record's first time stamps (the structs of testbed.wire.messages)
    times = [(4, 12, 20), (4, 12, 20), (4, 12), (4, 12, 20)]  # transport.ROLES' order
    tmpl = [bytearray(r.encode()) for r in recs]
    jit = np.random.default_rng(0).integers(0, 200_000, size=(4096, 3)).tolist()
    sp = Spill(path)
    for k in range(n):
        t0 = k * Tn
        j = jit[k & 4095]
        for ri, b in enumerate(tmpl):
            b[0:4] = k.to_bytes(4, "little")
            for i, off in enumerate(times[ri]):
                b[off:off + 8] = (t0 + (j[i] if ri == 0 else j[i] * (ri + 1))).to_bytes(8, "little", signed=True)
            sp.write(ri, bytes(b))
    final = msg.PlantTelemetry(k=n, t_ns=n * Tn, sensor_tx_ns=0, u_rx_ns=msg.NO_TIME, delay_ns=0, theta=0,
                               flags=msg.PlantTelemetry.FLAG_FINAL, flow_status=0, x=(0.1, 0.1), u=())
    sp.close()
    return final


def synthetic_summary_peak(n: int, tmp: str | Path, traced: bool = True) -> dict:
    """The launcher's end of run in-process on a synthetic spill of ``n`` samples at 1 kHz: the summary
    built from the spill and written as ``testbed run --json`` writes it (to a sink), its peak memory
    (tracemalloc: Python objects and numpy arrays; ``traced=False``: not measured, 0) and its time (tracemalloc
    slows Python down: time it untraced)."""
    import tracemalloc

    from testbed import scenario
    from testbed.live.collect import SpillRows
    from testbed.loop.quantizer import Codebook
    from testbed.record.summary import LIVE_FIELDS, build_summary, write_json
    from testbed.wire.transport import ROLES

    sc = scenario.with_overrides(scenario.load("paper"), {"T": 0.001, "duration": n * 0.001})
    path = Path(tmp) / f"telemetry-{n}.bin"
    final = synthetic_spill(path, sc, n)

    class Sink:
        chars = 0

        def write(self, s):
            Sink.chars += len(s)

    t = time.perf_counter()
    if traced:
        tracemalloc.start()
    try:  # as the launcher makes it (``Launcher.summarize``): rows a chunk at a time, per-sample values in files
        # the lag and each node's last sample as the collector counts them as records arrive (in order here)
        rows = SpillRows(sc, path, n, 0, LIVE_FIELDS, plant_final=final, top={r: n - 1 for r in ROLES})
        s = build_summary(sc, rows, run_id="synthetic", ack_via_attacker=False, nodes={}, faults=[],
                          codebook=Codebook(2, 6, True), arrays=True, store=tmp)
        write_json(s, Sink())
        peak = tracemalloc.get_traced_memory()[1] if traced else 0
    finally:
        tracemalloc.stop()
        path.unlink()
    return {"samples": n, "peak_mb": peak / 2**20, "seconds": time.perf_counter() - t, "json_chars": Sink.chars,
            "summary_samples": s["samples"]}


def mcap_index_main(hours: float, channels: int = 9, flush_interval: float = 0.5) -> int:
    """The memory mcap's ``Writer`` keeps for the file's summary section (a chunk index a closed chunk): the
    recorder's ``Writer`` settings, ``channels`` channels, a chunk closed every ``flush_interval`` s of
    ``hours`` (the recorder's flush), a few messages each, written to a sink; tracemalloc's figure."""
    import io
    import tracemalloc

    from mcap.writer import CompressionType, Writer

    class Sink(io.RawIOBase):
        n = 0

        def write(self, b) -> int:
            self.n += len(b)
            return len(b)

        def writable(self) -> bool:
            return True

        def tell(self) -> int:
            return self.n

    w = Writer(Sink(), chunk_size=1 << 20, compression=CompressionType.ZSTD, enable_data_crcs=True)
    w.start()
    sid = w.register_schema("s", "protobuf", b"")
    ch = [w.register_channel(f"/t{i}", "protobuf", sid) for i in range(channels)]
    chunks = int(hours * 3600 / flush_interval)
    tracemalloc.start()
    t = 0
    for _ in range(chunks):
        for c in ch:
            w.add_message(c, log_time=t, data=b"x" * 20, publish_time=t)
            t += 1
        w.flush()
    held = tracemalloc.get_traced_memory()[0]
    print(f"mcap's Writer after {chunks} chunks ({hours:g} h of a chunk every {flush_interval:g} s, {channels} "
          f"channels): {held / 1e6:.1f} MB held, {held / max(chunks, 1):.0f} bytes a chunk, "
          f"{held / 1e6 / hours:.1f} MB/h")
    return 0


def synthetic_main(spec: str, json_out: str | None) -> int:
    try:
        ns = [int(v) for v in spec.split(",")]
    except ValueError:
        print(f"bench_soak: --synthetic {spec!r}: sample counts separated by commas", file=sys.stderr)
        return 2
    if not all(n > 0 for n in ns):
        print("bench_soak: --synthetic: the sample counts must be positive", file=sys.stderr)
        return 2
    print("the launcher's end of run on a synthetic spill (in-process; tracemalloc's peak: Python objects "
          "and numpy arrays)")
    print(f"{'samples':>9} {'peak MB':>8} {'ratio':>6} {'seconds':>8}  (seconds: a second pass, untraced)")
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        synthetic_summary_peak(min(min(ns), 2000), tmp)  # the modules' and kernels' first use, out of the figures
        for n in ns:
            r = synthetic_summary_peak(n, tmp)
            r["seconds_traced"], r["seconds"] = r["seconds"], synthetic_summary_peak(n, tmp, traced=False)["seconds"]
            out.append(r)
            r["ratio"] = r["peak_mb"] / out[0]["peak_mb"]
            print(f"{n:9d} {r['peak_mb']:8.1f} {r['ratio']:6.2f} {r['seconds']:8.1f}", flush=True)
    if json_out:
        Path(json_out).write_text(json.dumps({"synthetic": out}, indent=1))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="length of the live run (default %(default)s)")
    ap.add_argument("--durations", metavar="S,S,...",
                    help="several runs, one after the other, of these lengths in seconds (instead of --minutes)")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--T", type=float, default=0.01, help="sample period, s (default %(default)s)")
    g.add_argument("--rate", type=float, metavar="HZ", help="sample rate (instead of --T: T = 1/HZ)")
    ap.add_argument("--every", type=float, default=None, metavar="S",
                    help="seconds between two readings (default: 30, or the run's length / 20 if shorter)")
    ap.add_argument("--warmup", type=float, default=None, metavar="S",
                    help="seconds left out of the growth figure (default: 60, or half the run if shorter)")
    ap.add_argument("--out", help="the recording (default: a temporary file, removed)")
    ap.add_argument("--json", metavar="FILE", help="also write every reading and the figures as JSON")
    ap.add_argument("--synthetic", metavar="N,N,...",
                    help="no live run: the launcher's end of run in-process on synthetic spills of these many "
                         "samples at 1 kHz, its peak memory (tracemalloc) and the ratio to the smallest's")
    ap.add_argument("--starve-recorder", metavar="ON,OFF",
                    help="while the loop runs, stop and continue the recorder in a cycle of ON ms running and OFF ms "
                         "stopped (as a niced recorder on a loaded machine: its writer falls behind)")
    ap.add_argument("--mcap-index", type=float, metavar="HOURS",
                    help="no live run: the memory mcap's Writer keeps for the file's index after HOURS of the "
                         "recorder's flushes (a chunk every 0.5 s, 9 channels)")
    ap.add_argument("--one-of", type=int, help=argparse.SUPPRESS)  # the run of this index only: a fresh process
    ap.add_argument("--result", help=argparse.SUPPRESS)             # ... writes its figures here
    a = ap.parse_args(argv)
    if a.starve_recorder:
        spec = a.starve_recorder
        try:
            a.starve_recorder = tuple(float(v) for v in spec.split(","))
            if len(a.starve_recorder) != 2 or not all(v > 0 for v in a.starve_recorder):
                raise ValueError
        except ValueError:
            print(f"bench_soak: --starve-recorder {spec!r}: two positive numbers of ms, ON,OFF", file=sys.stderr)
            return 2
    if a.synthetic:
        return synthetic_main(a.synthetic, a.json)
    if a.mcap_index:
        return mcap_index_main(a.mcap_index)
    if a.rate is not None:
        a.T = 1.0 / a.rate if a.rate > 0 else -1.0
    try:
        durs = [float(d) for d in a.durations.split(",")] if a.durations else [a.minutes * 60]
    except ValueError:
        print(f"bench_soak: --durations {a.durations!r}: seconds separated by commas", file=sys.stderr)
        return 2
    if not all(d > 0 for d in durs) or not a.T > 0:
        print("bench_soak: the durations (--minutes, --durations) and --T or --rate must be positive", file=sys.stderr)
        return 2
    if a.one_of is not None:  # one run, in this fresh process (see below)
        dur = durs[a.one_of]
        r = soak(dur, a, a.every or min(30.0, max(1.0, dur / 20)),
                 a.warmup if a.warmup is not None else min(60.0, dur / 2))
        if r is None:
            return 1
        Path(a.result).write_text(json.dumps(r))
        return 0
    # Each run is made by a fresh process of this script: ``wait4``'s ru_maxrss of the launcher counts the memory of
    # the process that forked it (the kernel carries the parent's peak across fork and exec), and this process,
    # having parsed a long run's --json summary, holds hundreds of MB (a 20-minute run's peak at 1 kHz read 880 MB
    # that way after a 5-minute run, where the launcher itself peaked at about 300 MB).
    runs = []
    argv = list(sys.argv[1:] if argv is None else argv)
    with tempfile.TemporaryDirectory(prefix="bench-soak-") as tmp:
        for i in range(len(durs)):
            res = Path(tmp) / f"run-{i}.json"
            sys.stdout.flush()
            rc = subprocess.run([sys.executable, os.path.abspath(__file__), *argv, "--one-of", str(i),
                                 "--result", str(res)]).returncode
            if rc != 0 or not res.exists():
                return 1
            runs.append(json.loads(res.read_text()))
    if len(runs) > 1:
        base = min(runs, key=lambda r: r["duration_s"])
        b = base["peak_mb"].get("launcher")
        print(f"\nthe launcher's peak (VmHWM, the end of the run included) against the run's length "
              f"(T = {a.T:g} s; goal: within {GOAL_PEAK_RATIO:g}x the shortest run's):")
        print(f"{'duration':>9} {'samples':>9} {'recorded':>9} {'all':>4} {'peak MB':>8} {'ratio':>6}")
        for r in runs:
            pk = r["peak_mb"].get("launcher")
            ratio = pk / b if pk and b else None
            r["launcher_peak_ratio"] = ratio
            rc = r["recording"]
            r["every_sample_recorded"] = every = (rc["recorded_samples"] == rc["run_samples"] == rc["n_steps"]
                                                  and bool(rc["recording_complete"]))
            print(f"{r['duration_s']:8g}s {rc['run_samples'] or 0:9d} {rc['recorded_samples'] or 0:9d} "
                  f"{'yes' if every else 'NO':>4} {pk or float('nan'):8.1f} "
                  + ("     ?" if ratio is None else f"{ratio:6.2f}"))
    if a.json:
        Path(a.json).write_text(json.dumps(runs[0] if len(runs) == 1 else {"runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
