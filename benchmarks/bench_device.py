"""Device benchmark: what the C plant on zenoh-pico costs in latency against the Python plant, same run.

Runs the paper's example in the router topology over mutual TLS (``testbed run paper --topology router
--tls-dir DIR --external plant``), with the plant joined from outside through the join file: once the C
device (``devices/pico-plant``, built by its ``build.sh`` unless ``--device`` names a binary) and once the
bundled Python plant (``testbed node plant``), alternating, ``--repeats`` times each.  Per run it reads the
launcher's timing (``testbed run --json``): the sampling jitter, sensor-to-actuator and the plant's stage
(u_k published by the controller to received by the plant), and prints the medians over the repeats of
each figure's p50 and p99 with the spread (min..max), and the device's median over the Python plant's as
a ratio: the Python plant is the baseline measured in the same invocation.

    python benchmarks/bench_device.py --duration 20 --repeats 3
    python benchmarks/bench_device.py --device /path/tb-pico-plant --duration 10 --repeats 1 --json dev.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
JOIN_LINE = "testbed run: join file for the external plant: "
#: the figures compared, (label, path in the summary's ``timing``)
FIGURES = (("sampling jitter", ("sampling_jitter_us",)), ("sensor-to-actuator", ("sensor_to_actuator_us",)),
           ("plant stage", ("stages_us", "plant")))


def testbed_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "testbed.cli", *args]


def build_device() -> str:
    out = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "testbed" / "pico-plant"
    p = subprocess.run(["bash", str(ROOT / "devices" / "pico-plant" / "build.sh"), str(out)],
                       capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit(f"bench_device: the device did not build:\n{p.stderr[-2000:]}")
    return p.stdout.strip().splitlines()[-1]


def one_run(plant_cmd: list[str], tls: str, duration: float, timeout: float) -> dict:
    """One run with ``plant_cmd`` as the external plant: the launcher's summary (``testbed run --json``)."""
    run = subprocess.Popen(testbed_cmd("run", "paper", "--topology", "router", "--tls-dir", tls, "--external",
                                       "plant", "--json", "--no-record", "--duration", f"{duration:g}"),
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    found, err = threading.Event(), []

    def read_stderr():
        for line in run.stderr:
            err.append(line)
            if line.startswith(JOIN_LINE):
                found.set()
        found.set()

    threading.Thread(target=read_stderr, daemon=True).start()
    node = None
    try:
        if not found.wait(timeout) or not any(line.startswith(JOIN_LINE) for line in err):
            raise RuntimeError("no join file:\n" + "".join(err[-20:]))
        join = next(line for line in err if line.startswith(JOIN_LINE))[len(JOIN_LINE):].strip()
        node = subprocess.Popen(plant_cmd, env={**os.environ, "TESTBED_JOIN": join}, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)
        out, _ = run.communicate(timeout=duration + timeout)
        node.wait(timeout=30)
    finally:
        for p in (run, node):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
    return json.loads(out)


def figure(summary: dict, path: tuple[str, ...]) -> dict | None:
    v = summary.get("timing") or {}
    for key in path:
        v = (v or {}).get(key)
    return v if isinstance(v, dict) and v.get("p50") is not None else None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", help="the tb-pico-plant binary (default: build it with devices/pico-plant/build.sh)")
    ap.add_argument("--duration", type=float, default=20.0, help="seconds per run (default %(default)s)")
    ap.add_argument("--repeats", type=int, default=3, help="runs of each plant, alternating (default %(default)s)")
    ap.add_argument("--timeout", type=float, default=120.0, help="start-up timeout per run, s")
    ap.add_argument("--json", metavar="FILE", help="write every run's figures and the medians to FILE")
    a = ap.parse_args(argv)
    device = a.device or build_device()
    plants = {"device": [device], "python": testbed_cmd("node", "plant")}
    runs: dict[str, list[dict]] = {k: [] for k in plants}
    with tempfile.TemporaryDirectory() as tmp:
        tls = str(Path(tmp) / "tls")
        subprocess.run(testbed_cmd("secret", tls, "--tls"), check=True, capture_output=True)
        for i in range(a.repeats):
            for name, cmd in plants.items():
                s = one_run(cmd, tls, a.duration, a.timeout)
                fig = {label: figure(s, path) for label, path in FIGURES}
                fig["deadline_misses"] = (s.get("timing") or {}).get("deadline_misses")
                fig["outcome"] = s.get("outcome")
                runs[name].append(fig)
                print(f"run {i + 1}/{a.repeats} {name}: outcome {fig['outcome']}, deadline misses "
                      f"{fig['deadline_misses']}", flush=True)
    print(f"\nmedian over {a.repeats} runs of {a.duration:g} s each (min..max); ratio = device / python plant")
    medians = {}
    for label, _ in FIGURES:
        for q in ("p50", "p99"):
            row = {}
            for name in plants:
                vals = [f[label][q] for f in runs[name] if f[label]]
                row[name] = (statistics.median(vals), min(vals), max(vals)) if vals else None
            d, p = row["device"], row["python"]
            ratio = d[0] / p[0] if d and p and p[0] > 0 else None
            medians[f"{label} {q}"] = {"device": d, "python": p, "ratio": ratio}

            def fmt(v):
                return "n/a" if v is None else f"{v[0]:8.1f} us ({v[1]:.1f}..{v[2]:.1f})"

            print(f"  {label + ' ' + q:22s} device {fmt(d)}   python {fmt(p)}   ratio "
                  + ("n/a" if ratio is None else f"{ratio:.2f}x"))
    if a.json:
        Path(a.json).write_text(json.dumps({"duration": a.duration, "repeats": a.repeats, "runs": runs,
                                            "medians": medians}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
