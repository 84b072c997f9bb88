"""Does the live Rerun stream disturb the loop?  The same live run with and without ``--rerun save``.

For each sample period T it runs ``testbed run SCENARIO --T T --json`` twice (or
``--reps`` times each, alternating): without Rerun and with ``--rerun save
PATH.rrd`` (every node streams its telemetry from a background thread; the
launcher merges the parts), MCAP recording off in both so that only Rerun differs.
It prints sampling jitter p50 / p99 / max, sensor-to-actuator latency p50 / p99 /
max, deadline misses, and the ratios with / without.

    python benchmarks/bench_rerun.py                         # T = 0.1 s (20 s) and T = 0.005 s (10 s)
    python benchmarks/bench_rerun.py --periods 0.1 0.01 --duration 10 --reps 2
    python benchmarks/bench_rerun.py --periods 0.005 --sinks save connect --reps 2   # live-view sink too
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run_once(scenario: str, T: float, duration: float, rrd: str | None, sink: str = "save") -> dict:
    """One live run; ``rrd`` None: no Rerun.  ``sink`` "save": ``--rerun save rrd``; "connect":
    ``--rerun connect`` to a headless Rerun gRPC server (``rerun --port P --save rrd``, what a
    viewer's server does minus the drawing), started here and stopped after the run."""
    cmd = [sys.executable, "-m", "testbed.cli", "run", scenario, "--T", repr(T), "--duration", repr(duration),
           "--json", "--no-record"]
    env = dict(os.environ, RERUN_ANALYTICS="0")
    with contextlib.ExitStack() as stack:
        if rrd and sink == "connect":
            from testbed.view.rerun import saving_server

            cmd += ["--rerun", "connect", stack.enter_context(saving_server(rrd))]
        elif rrd:
            cmd += ["--rerun", "save", rrd]
        t0 = time.monotonic()
        p = subprocess.run(cmd, capture_output=True, timeout=duration + 180, env=env)
    wall = time.monotonic() - t0
    if not p.stdout.strip():
        raise SystemExit(f"testbed run failed ({p.returncode}): {p.stderr.decode()[-2000:]}")
    s = json.loads(p.stdout)
    tm = s["timing"]
    out = {"T": T, "rerun": sink if rrd else False, "exit": p.returncode, "samples": s["samples"], "wall_s": round(wall, 1),
           "jitter_us": tm["sampling_jitter_us"], "s2a_us": tm["sensor_to_actuator_us"],
           "deadline_misses": tm["deadline_misses"], "faults": len(s["faults"]),
           # CPU seconds of the four nodes during the loop (every thread: the loop's, Zenoh's, Rerun's):
           # steadier than the misses on a noisy machine
           "nodes_cpu_s": round(sum((s["node_summaries"].get(r) or {}).get("cpu_run_s") or 0.0
                                    for r in ("plant", "encoder", "attacker", "controller")), 2)}
    if rrd:
        out["rrd_bytes"] = Path(rrd).stat().st_size if Path(rrd).exists() else None
        out["rerun_summary"] = s.get("rerun")
    return out


def fmt(p: dict | None) -> str:
    if not p or p.get("p50") is None:
        return "n/a"
    return f"{p['p50']:8.1f} {p['p99']:8.1f} {p['max']:8.1f}"


def ratio(a: dict, b: dict, key: str) -> str:
    try:
        return f"{a[key] / b[key]:.2f}" if b[key] else "n/a"
    except (KeyError, TypeError):
        return "n/a"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="paper")
    ap.add_argument("--periods", type=float, nargs="+", default=[0.1, 0.005])
    ap.add_argument("--duration", type=float, help="seconds per run (default 20 at T >= 0.05, else 10)")
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--sinks", nargs="+", choices=("save", "connect"), default=["save"],
                    help="Rerun sinks to compare with no Rerun (default: save)")
    ap.add_argument("--json", metavar="PATH")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-rerun-") as tmp:
        for T in args.periods:
            dur = args.duration or (20.0 if T >= 0.05 else 10.0)
            for rep in range(args.reps):
                for sink in (None, *args.sinks):
                    rrd = str(Path(tmp) / f"T{T}-{rep}-{sink}.rrd") if sink else None
                    r = run_once(args.scenario, T, dur, rrd, sink or "save")
                    rows.append(r)
                    print(f"# T={T:g} rerun={sink or 'off'} rep {rep}: {r['samples']} samples, "
                          f"exit {r['exit']}, wall {r['wall_s']} s", file=sys.stderr)
    print(f"{'T (s)':>7} {'rerun':>7} {'samples':>7} | {'jitter p50':>9} {'p99':>8} {'max (us)':>8} | "
          f"{'s->a p50':>8} {'p99':>8} {'max (us)':>8} | misses | node CPU s")
    for r in rows:
        print(f"{r['T']:7g} {(r['rerun'] or 'off'):>7} {r['samples']:7d} | {fmt(r['jitter_us']):>26} | "
              f"{fmt(r['s2a_us']):>26} | {r['deadline_misses']:>6} | {r['nodes_cpu_s']:>6.2f}")
    print("\nratio rerun on / off (first rep):")
    for T, sink in ((T, sink) for T in args.periods for sink in args.sinks):
        off = next(r for r in rows if r["T"] == T and not r["rerun"])
        on = next(r for r in rows if r["T"] == T and r["rerun"] == sink)
        print(f"  T={T:g} {sink}: jitter p50 {ratio(on['jitter_us'], off['jitter_us'], 'p50')}, "
              f"p99 {ratio(on['jitter_us'], off['jitter_us'], 'p99')}, "
              f"max {ratio(on['jitter_us'], off['jitter_us'], 'max')}; "
              f"sensor-to-actuator p50 {ratio(on['s2a_us'], off['s2a_us'], 'p50')}, "
              f"p99 {ratio(on['s2a_us'], off['s2a_us'], 'p99')}; .rrd {on.get('rrd_bytes')} bytes")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
