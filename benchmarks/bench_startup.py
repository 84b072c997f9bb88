"""Start-up benchmark: how long ``testbed run SCENARIO --duration 1 --no-record`` takes, and where the time goes.

Runs the command ``--reps`` times (default 3) with ``-v``, so that the launcher and every node
log their milestones (``phase NAME t=...``), and prints for each phase the median time since the
command was started, then the median wall time from command to exit:

    launcher  up (Python and imports), scenario (loaded), router (its Zenoh session), spawned
    each node up (Python and imports), scenario, session (connected to the router), warm (declared and
              JIT-warm), peers (saw every node alive), start (the plant's Start received), end, closing
    t0        sample 0
    launcher  watched (every node exited), stopped, summary; exit

    python benchmarks/bench_startup.py                       # paper, 3 runs
    python benchmarks/bench_startup.py --reps 5 --json startup.json
    python benchmarks/bench_startup.py -- --colocate encoder # extra flags after -- go to testbed run
    python benchmarks/bench_startup.py --baseline ../other-checkout  # A/B: that checkout's code, run by turns

``--baseline DIR`` runs every repetition twice, first with the code of another checkout of the
project (``PYTHONPATH=DIR``, e.g. a worktree of ``main``), then with this one, and prints both
medians: the A/B of the start-up changes in one invocation.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from testbed.wire.transport import ROLES

PHASE = re.compile(r"(?:testbed run|(\w+)): phase (\w+) t=([0-9.]+)")
T0 = re.compile(r"start, t0 = (\d+)")


def one_run(scenario: str, duration: float, extra: list[str], code: str | None = None) -> dict:
    """One timed run: wall seconds and {who: {phase: seconds since the command}}.

    ``code``: another checkout of the project to run instead (``PYTHONPATH``)."""
    env = dict(os.environ)
    if code:
        env["PYTHONPATH"] = os.path.abspath(code)
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as d:
        cmd = [sys.executable, "-m", "testbed.cli", "run", scenario, "--duration", str(duration), "--no-record",
               "-v", "--run-dir", d, *extra]
        t_cmd = time.time()
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env, cwd=code or None)
        wall = time.time() - t_cmd
        if p.returncode != 0:
            raise SystemExit(f"testbed run failed (exit {p.returncode}):\n{p.stderr[-3000:]}")
        phases: dict[str, dict[str, float]] = {"launcher": {}}
        t0 = None
        for line in p.stderr.splitlines():
            m = PHASE.search(line)
            if m and line.startswith("testbed run:"):
                phases["launcher"][m.group(2)] = float(m.group(3)) - t_cmd
        for f in Path(d).glob("*.log"):
            who = f.stem
            for line in f.read_text(errors="replace").splitlines():
                m = PHASE.search(line)
                if m:
                    phases.setdefault(who, {})[m.group(2)] = float(m.group(3)) - t_cmd
                m = T0.search(line)
                if m and t0 is None:
                    t0 = int(m.group(1)) / 1e9 - t_cmd
        phases["launcher"]["exit"] = wall
        return {"wall_s": wall, "t0_s": t0, "phases": phases}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="paper", help="scenario (default %(default)s)")
    ap.add_argument("--duration", type=float, default=1.0, help="run duration in seconds (default %(default)s)")
    ap.add_argument("--reps", type=int, default=3, help="runs; the figures are medians (default %(default)s)")
    ap.add_argument("--json", metavar="FILE", help="write every run's phases as JSON")
    ap.add_argument("--baseline", metavar="DIR", help="also run another checkout's code, by turns (A/B)")
    args, extra = ap.parse_known_args()
    extra = [a for a in extra if a != "--"]
    print(f"host: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}; testbed run {args.scenario} "
          f"--duration {args.duration:g} --no-record {' '.join(extra)}")
    runs, base = [], []
    for i in range(args.reps):
        if args.baseline:
            b = one_run(args.scenario, args.duration, extra, args.baseline)
            base.append(b)
            print(f"  run {i + 1}, baseline {args.baseline}: {b['wall_s']:.2f} s wall, sample 0 at "
                  f"{b['t0_s']:.2f} s")
        r = one_run(args.scenario, args.duration, extra)
        runs.append(r)
        print(f"  run {i + 1}: {r['wall_s']:.2f} s wall, sample 0 at {r['t0_s']:.2f} s")

    def med(who, ph):
        v = [r["phases"].get(who, {}).get(ph) for r in runs]
        v = [x for x in v if x is not None]
        return statistics.median(v) if v else None

    whos = ["launcher"] + [w for w in ROLES if any(w in r["phases"] for r in runs)]
    names = []
    for r in runs:
        for who in whos:
            for ph in r["phases"].get(who, {}):
                if ph not in names:
                    names.append(ph)
    print(f"\nmedian seconds since the command ({args.reps} runs)")
    print(f"  {'phase':10s}" + "".join(f"{w:>11s}" for w in whos))
    for ph in names:
        cells = []
        for who in whos:
            v = med(who, ph)
            cells.append(f"{v:11.2f}" if v is not None else f"{'':11s}")
        print(f"  {ph:10s}" + "".join(cells))
    t0 = statistics.median(r["t0_s"] for r in runs if r["t0_s"] is not None)
    wall = statistics.median(r["wall_s"] for r in runs)
    print(f"\n  sample 0 at {t0:.2f} s; exit at {wall:.2f} s (median of {args.reps}); "
          f"after the last sample: {wall - t0 - args.duration:.2f} s")
    out = {"wall_s_median": wall, "t0_s_median": t0, "runs": runs}
    if base:
        bw = statistics.median(r["wall_s"] for r in base)
        bt = statistics.median(r["t0_s"] for r in base if r["t0_s"] is not None)
        print(f"  baseline ({args.baseline}): sample 0 at {bt:.2f} s, exit at {bw:.2f} s; "
              f"this checkout takes {wall / bw:.2f}x the baseline's wall time")
        out.update(baseline=args.baseline, baseline_wall_s_median=bw, baseline_t0_s_median=bt, baseline_runs=base)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
