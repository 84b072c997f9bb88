"""Simulated campaign runs per second on 1 and 2 workers, against the same runs as separate
``testbed simulate`` processes, in one invocation.

It writes a random-attack version of the paper's example (``docs/examples/paper-random.toml``,
``--duration`` seconds) and a campaign of 2 methods x ``--seeds`` attack seeds, runs it with
``testbed campaign --workers 1`` and ``--workers 2`` (each in a fresh folder: nothing skipped),
then ``--separate`` of its runs as one ``testbed simulate --method M --seed S --json`` process
each (one after the other, as a shell loop would), and prints runs per second of each, and the
campaign's as a ratio to the separate processes' (the baseline, measured in the same run).  The
campaign's times include its process start-up and its writing of the table; the separate runs'
are per process.

    python benchmarks/bench_campaign.py                        # 2 x 100 runs of 30 s, 20 separate
    python benchmarks/bench_campaign.py --seeds 20 --duration 10 --separate 5
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=100, help="attack seeds per method (default 100)")
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of each run (default 30)")
    ap.add_argument("--separate", type=int, default=20, help="runs timed as separate processes (default 20)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-campaign-") as d:
        d = Path(d)
        text = (ROOT / "docs" / "examples" / "paper-random.toml").read_text()
        text = re.sub(r"(?m)^duration = .*$", f"duration = {a.duration!r}", text)
        (d / "random.toml").write_text(text)
        seeds = list(range(a.seeds))
        (d / "c.toml").write_text(f'scenario = "random.toml"\nseed = 1\n[axes]\n"method.name" = ["paper", "zoom"]\n'
                                  f'"attack.seed" = {json.dumps(seeds)}\n')
        n = 2 * a.seeds
        out = {"runs": n, "duration_s": a.duration}
        for w in a.workers:
            t0 = time.perf_counter()
            p = subprocess.run([sys.executable, "-m", "testbed.cli", "campaign", "c.toml", "--out", f"w{w}",
                                "--workers", str(w), "--no-progress", "--json"], cwd=d, capture_output=True, text=True)
            el = time.perf_counter() - t0
            if p.returncode != 0:
                raise SystemExit(f"campaign failed ({p.returncode}): {p.stderr[-2000:]}")
            out[f"campaign_{w}_workers"] = {"wall_s": round(el, 2), "runs_per_s": round(n / el, 2)}
        k = min(a.separate, n)
        t0 = time.perf_counter()
        for i in range(k):
            m, s = ("paper", "zoom")[i % 2], seeds[i // 2]
            p = subprocess.run([sys.executable, "-m", "testbed.cli", "simulate", "random.toml", "--method", m,
                                "--seed", str(s), "--json"], cwd=d, capture_output=True, text=True)
            if p.returncode != 0:
                raise SystemExit(f"simulate failed ({p.returncode}): {p.stderr[-2000:]}")
        el = time.perf_counter() - t0
        out["separate_processes"] = {"runs": k, "wall_s": round(el, 2), "runs_per_s": round(k / el, 2)}
    base = k / el  # the baseline: a shell loop of `testbed simulate` processes, measured in the same run
    for w in a.workers:
        c = out[f"campaign_{w}_workers"]
        c["vs_separate_processes"] = round(c["runs_per_s"] / base, 2)
    if len(a.workers) > 1:
        w0 = out[f"campaign_{a.workers[0]}_workers"]["runs_per_s"]
        out["speedup_workers"] = {str(w): round(out[f"campaign_{w}_workers"]["runs_per_s"] / w0, 2) for w in a.workers}
    print(json.dumps(out, indent=1))
    for w in a.workers:
        c = out[f"campaign_{w}_workers"]
        print(f"campaign, {w} worker(s): {c['runs_per_s']} runs/s = {c['vs_separate_processes']}x separate processes "
              f"({out['separate_processes']['runs_per_s']} runs/s)", file=sys.stderr)


if __name__ == "__main__":
    main()
