"""Live-loop timing benchmark: T = 0.1 s, 2 ms and 1 ms over Zenoh on loopback, against floors measured in the same run.

For each sample period T it measures, in one invocation:

1. the floor: a bare Zenoh ping-pong between two Python processes (same config,
   QoS and message sizes as the control path: 1-byte payload, 12-byte header),
   one ping per period T, so the messages are as sparse as in the loop.  The loop
   crosses four one-way hops (plant -> encoder -> attacker -> controller -> plant),
   two round trips, so the four-hop floor is 2 x the ping-pong RTT, and
   ``ideal_misses_per_10k`` is how many of 10,000 deadlines an ideal loop of two
   consecutive measured round trips would miss;
2. the floor with the work: the same four hops between two processes, the echo
   doing the encoder's and the controller's per-sample work (decode, quantizer
   update, encode, through ``testbed.loop.protocol`` and ``testbed.wire.messages`` as
   the nodes do) and the pinger the attacker's forward and the plant's decode
   and flow map, its u_k checked against the simulator's.  Its excess over 2 x RTT
   is what our code costs per sample; the live loop's excess over it is what the
   node shells and the topology cost;
3. the live loop: ``testbed run`` of the paper's plant and gain at period T
   (no DoS, so every sample should make it), for ``--duration`` seconds, once per
   variant: by default ``default`` (``--topology auto``: the peer topology on one
   host) and ``router`` (``--topology router``, the router topology).

It prints p50 / p99 sampling jitter, p50 / p99 sensor-to-actuator latency and its
stages (encoder, proxy, controller, plant), deadline misses, CPU share per node,
and the goals as ratios to the floors of the same run: at T = 0.1 s the p50 over
the four-hop floor (goal <= 1.2x), at T = 2 ms the deadline misses over the ideal
four-hop loop's (goal <= 2x), at T = 1 ms both.

``--variants`` picks the live-loop variants (``VARIANTS``: the flags of ``testbed
run``; combine with ``+``, e.g. ``colocated+low-latency``), run one after the
other at each period so that a change is measured as an A/B against the first.
``--auth`` is ``--variants default,insecure``: the latency cost of authentication.
``--ab`` runs the A/B of every change of the faster loop (``AB_SET``).  ``--table
FILE.json`` prints the Markdown table of ``docs/benchmarks.md`` from a ``--json`` file.

    python benchmarks/bench_live.py --duration 20 --json live.json   # default, router, floors at 0.1 s, 2 ms, 1 ms
    python benchmarks/bench_live.py --duration 10 --periods 0.001 --realtime --json out.json
    python benchmarks/bench_live.py --auth --periods 0.1 --duration 20
    python benchmarks/bench_live.py --ab --periods 0.1,0.002 --duration 20 --json live.json
    python benchmarks/bench_live.py --table live.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

SCENARIO = """\
# benchmark: the paper's plant and gain at period T, no DoS
name = "bench-T{tag}"
[plant]
name = "lienard"
params = {{ a = 0.3333333333333333, b = 0.02 }}
x0 = [0.1, 0.1]
[quantizer]
T = {T!r}
M = 6
L = 10.0
E0 = 0.1
E_min = 1e-9          # keeps E_k above the round-off level over 30 000 samples
mode = "resilient"
[controller]
K = [[-1.81, -1.90]]
[attack]
kind = "none"
[run]
duration = {duration!r}
deadline = {deadline!r}
"""


# ------------------------------------------------------------------ ping-pong floor
def _config(listen=(), connect=()):
    from testbed.wire import transport

    return transport.make_config(listen=list(listen), connect=list(connect))


def echo_main(port: int, seconds: float, realtime: bool) -> None:
    import zenoh

    from testbed.nodes.process import set_realtime, tune_process
    from testbed.wire import transport

    tune_process()
    with zenoh.open(_config(listen=[f"tcp/127.0.0.1:{port}"])) as s:
        pub = s.declare_publisher("bench/pong", **transport.control_qos())
        s.declare_subscriber("bench/ping", lambda smp: pub.put(smp.payload, attachment=smp.attachment))
        if realtime:
            set_realtime(True)
        try:
            time.sleep(seconds)
        except KeyboardInterrupt:
            pass


def ping_pong(T: float, seconds: float, realtime: bool, budget: float | None = None) -> dict:
    """RTT of a bare Zenoh ping-pong paced at period T (same pacing as the plant).

    ``budget`` (s, the plant's deadline d T): also the floor of the deadline misses, ``ideal_misses_per_10k``:
    how many of 10,000 samples an ideal loop would miss whose hops each took half a measured round trip and
    nothing else (four hops: two consecutive RTTs; three, with ``--colocate encoder``: one and a half).

    The echo listens on a port found free a moment before; another process may take it in
    between, so a ping-pong whose echo died is tried again on a new port (three times).
    """
    for attempt in range(3):
        r = _ping_pong(T, seconds, realtime)
        if r is not None:
            rtt = r.pop("_rtt")
            if budget is not None and rtt.size > 1:
                b = budget * 1e6
                r["ideal_misses_per_10k"] = {
                    "4 hops": round(float(np.mean(rtt[:-1] + rtt[1:] > b)) * 1e4, 1),
                    "3 hops": round(float(np.mean(rtt[:-1] + rtt[1:] / 2 > b)) * 1e4, 1)}
            return r
        print(f"  ping-pong: the echo did not come up (its port was taken?): attempt {attempt + 2}", file=sys.stderr)
    raise SystemExit("bench_live: the ping-pong echo did not come up three times")


def _ping_pong(T: float, seconds: float, realtime: bool) -> dict | None:
    import zenoh

    from testbed.nodes.clock import RunClock
    from testbed.nodes.process import set_realtime, tune_process
    from testbed.wire import messages as msg
    from testbed.wire import transport

    port = transport.free_port()
    n = int(max(50, min(seconds / T, 20000)))
    echo = subprocess.Popen([sys.executable, __file__, "--echo", str(port), "--echo-seconds",
                             str(n * T + 20)] + (["--realtime"] if realtime else []),
                            start_new_session=True)
    rtt = []
    try:
        tune_process()
        with zenoh.open(_config(connect=[f"tcp/127.0.0.1:{port}"])) as s:
            got = threading.Event()
            box = [0]

            def on_pong(_smp):
                box[0] = time.monotonic_ns()
                got.set()

            s.declare_subscriber("bench/pong", on_pong)
            pub = s.declare_publisher("bench/ping", **transport.control_qos())
            att = msg.Header(0, 0).encode()
            end = time.monotonic() + 20
            while time.monotonic() < end:  # wait for the echo and warm up
                got.clear()
                pub.put(b"\x00", attachment=att)
                if got.wait(0.2):
                    break
                if echo.poll() is not None:
                    return None
            for _ in range(20):
                got.clear()
                pub.put(b"\x00", attachment=att)
                got.wait(1)
            if realtime:
                set_realtime(True)
            clock = RunClock(time.time_ns() + 50_000_000)
            T_ns = int(round(T * 1e9))
            spin = min(200_000, T_ns // 20)
            for k in range(n):
                clock.sleep_until(k * T_ns, spin)
                got.clear()
                t = time.monotonic_ns()
                pub.put(b"\x00", attachment=att)
                if got.wait(max(T, 0.05)):
                    rtt.append(box[0] - t)
    finally:
        if realtime:
            set_realtime(False)
        os.killpg(echo.pid, signal.SIGINT)
        try:
            echo.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(echo.pid, signal.SIGKILL)
            echo.wait()
    a = np.array(rtt) / 1e3
    return {"n": int(a.size), "lost": n - int(a.size), "p50": float(np.percentile(a, 50)),
            "p99": float(np.percentile(a, 99)), "max": float(a.max()), "_rtt": a}


# ------------------------------------------------------------------ the floor with the work
# The loop's four hops between two processes: the pinger is the plant and the attacker, the echo
# the encoder and the controller.  Per sample: x_k (Sensor) -> echo: decode, Algorithm 1 (quantizer
# update), pack -> symbol -> pinger forwards it as the attacker does -> echo: unpack, Algorithm 2,
# control law (2), Actuation -> pinger: decode, the plant's flow map (off the clock).  Everything
# through the objects the nodes use (``testbed.loop.protocol``, ``testbed.wire.messages``); no node shell
# (threads, telemetry, locks, run clock), no router, no TLS.  Its u_k are checked against the
# simulator's for the same scenario.
def _work_objects(scenario_file: str, n: int):
    from testbed import scenario
    from testbed.loop.protocol import ControllerProtocol, EncoderProtocol

    sc = scenario.load(scenario_file)
    model = sc.make_model()
    m = sc.make_method()
    enc = EncoderProtocol(m.make_encoder(model, sc.K, sc.quantizer, sc.flow), n)
    ctl = ControllerProtocol(m.make_decoder(model, sc.K, sc.quantizer, sc.flow), n, defer_update=True)
    return sc, enc, ctl


def echo_work_main(port: int, seconds: float, realtime: bool, scenario_file: str, n: int) -> None:
    """The encoder's and the controller's per-sample work, as the echo of ``work_ping_pong``."""
    import zenoh

    from testbed.loop.protocol import Send
    from testbed.nodes.process import set_realtime, tune_process
    from testbed.wire import messages as msg
    from testbed.wire import transport

    tune_process()
    sc, enc, ctl = _work_objects(scenario_file, n)
    codebook = enc.enc.codebook
    lock = threading.Lock()
    with zenoh.open(_config(listen=[f"tcp/127.0.0.1:{port}"])) as s:
        pub_sym = s.declare_publisher("bench/symbol", **transport.control_qos())
        pub_act = s.declare_publisher("bench/actuation", **transport.control_qos())

        def on_sensor(smp):  # the encoder node's _on_sensor / sensor_in
            x = msg.Sensor.decode(smp.payload, smp.attachment)
            if x.k == msg.WARMUP_K:
                pub_sym.put(b"\0" * codebook.nbytes, attachment=smp.attachment)
                return
            with lock:
                while ctl.next_k < x.k:  # a sample whose symbol never came: the controller's loss deadline
                    d = ctl.deadline(ctl.next_k)
                    ctl.settle()
                    enc.ack(d.k, d.theta, d.last_rx)
                act = enc.sensor(x.k, x.x)
                if isinstance(act, Send):
                    pub_sym.put(codebook.pack(act.symbol), attachment=msg.Header(x.k, time.monotonic_ns()).encode())

        def on_symbol(smp):  # the controller node's _on_symbol / _publish
            h = msg.Header.decode(smp.attachment)
            if h.k == msg.WARMUP_K:
                p, a = msg.Actuation(msg.WARMUP_K, 0, 1, (0.0,) * np.asarray(sc.K).shape[0]).encode()
                pub_act.put(p, attachment=a)
                return
            with lock:
                decs = ctl.symbol(h.k, smp.payload.to_bytes())
                for d in decs:
                    p, a = msg.Actuation(d.k, time.monotonic_ns(), d.theta, tuple(d.u.tolist()), d.last_rx).encode()
                    pub_act.put(p, attachment=a)
                ctl.settle()
                for d in decs:  # the ack the encoder reads from the actuation message
                    enc.ack(d.k, d.theta, d.last_rx)

        s.declare_subscriber("bench/sensor", on_sensor)
        s.declare_subscriber("bench/symbol_rx", on_symbol)
        if realtime:
            set_realtime(True)
        try:
            time.sleep(seconds)
        except KeyboardInterrupt:
            pass


def work_ping_pong(T: float, seconds: float, realtime: bool, budget: float | None = None) -> dict:
    """The four hops of one sample with the encoder's, attacker's, controller's and plant's per-sample
    work (``echo_work_main``), paced at period T: p50 / p99 / max of x_k out -> u_k in (us), the same
    hops' bare figure (2 x the ping-pong RTT) is ``ping_pong``'s.  ``ideal_misses_per_10k``: the
    samples of 10,000 whose four hops with the work took longer than ``budget`` (s).  ``u_equals_simulator``:
    every u_k equals ``testbed simulate``'s for the same scenario (None when a sample was lost)."""
    for attempt in range(3):
        r = _work_ping_pong(T, seconds, realtime)
        if r is not None:
            lat = r.pop("_lat")
            if budget is not None and lat.size:
                r["ideal_misses_per_10k"] = round(float(np.mean(lat > budget * 1e6)) * 1e4, 1)
            return r
        print(f"  work ping-pong: the echo did not come up (its port was taken?): attempt {attempt + 2}",
              file=sys.stderr)
    raise SystemExit("bench_live: the work ping-pong echo did not come up three times")


def _work_ping_pong(T: float, seconds: float, realtime: bool) -> dict | None:
    import zenoh

    from testbed.loop.protocol import PlantProtocol
    from testbed.nodes.clock import RunClock
    from testbed.nodes.process import set_realtime, tune_process
    from testbed.wire import messages as msg
    from testbed.wire import transport

    port = transport.free_port()
    n = int(max(50, min(seconds / T, 20000)))
    d = tempfile.mkdtemp(prefix="bench-work-")
    f = Path(d) / "bench.toml"
    f.write_text(SCENARIO.format(tag=f"{T:g}".replace(".", "_"), T=T, duration=n * T, deadline=0.5))
    echo = subprocess.Popen([sys.executable, __file__, "--echo", str(port), "--echo-seconds", str(n * T + 30),
                             "--echo-work", str(f), "--echo-n", str(n)] + (["--realtime"] if realtime else []),
                            start_new_session=True)
    lat, us, lost = [], [], 0
    sc, _, _ = _work_objects(str(f), n)
    proc = sc.make_process()
    proc.reset(np.asarray(sc.x0, dtype=np.float64))
    plant = PlantProtocol.for_scenario(sc, proc)
    try:
        tune_process()
        with zenoh.open(_config(connect=[f"tcp/127.0.0.1:{port}"])) as s:
            got_sym, got_act = threading.Event(), threading.Event()
            box = {}

            def on_symbol(smp):  # the attacker's side: what arrived, forwarded below as it came
                box["sym"] = (msg.Header.decode(smp.attachment).k, smp.payload.to_bytes(), smp.attachment.to_bytes())
                got_sym.set()

            def on_act(smp):  # the plant's actuation handler
                a = msg.Actuation.decode(smp.payload, smp.attachment)
                box["act"] = (a, time.monotonic_ns())
                got_act.set()

            s.declare_subscriber("bench/symbol", on_symbol)
            s.declare_subscriber("bench/actuation", on_act)
            pub_x = s.declare_publisher("bench/sensor", **transport.control_qos())
            pub_fwd = s.declare_publisher("bench/symbol_rx", **transport.control_qos())
            warm_p, warm_a = msg.Sensor(msg.WARMUP_K, 0, tuple(sc.x0)).encode()
            end = time.monotonic() + 20
            up = False
            while time.monotonic() < end and not up:  # wait for the echo, then warm up both paths
                got_sym.clear()
                pub_x.put(warm_p, attachment=warm_a)
                up = got_sym.wait(0.2)
                if echo.poll() is not None:
                    return None
            for _ in range(20):
                got_sym.clear()
                got_act.clear()
                pub_x.put(warm_p, attachment=warm_a)
                if got_sym.wait(1):
                    k, p, a = box["sym"]
                    pub_fwd.put(p, attachment=a)
                    got_act.wait(1)
            if realtime:
                set_realtime(True)
            clock = RunClock(time.time_ns() + 50_000_000)
            T_ns = int(round(T * 1e9))
            spin = min(200_000, T_ns // 20)
            wait = max(T, 0.05)
            x = np.array(sc.x0, dtype=np.float64)
            for k in range(n):
                clock.sleep_until(k * T_ns, spin)
                got_sym.clear()
                got_act.clear()
                t = time.monotonic_ns()
                p, a = msg.Sensor(k, clock.now(), tuple(x.tolist())).encode()
                pub_x.put(p, attachment=a)
                u = None
                while got_sym.wait(wait):  # the symbol of sample k (a late one of an earlier sample is dropped)
                    got_sym.clear()
                    if box["sym"][0] == k:
                        _, p, a = box["sym"]
                        pub_fwd.put(p, attachment=a)
                        while got_act.wait(wait):
                            got_act.clear()
                            act, t_rx = box["act"]
                            if act.k == k:
                                u = np.array(act.u)
                                lat.append(t_rx - t)
                                break
                        break
                if u is None:
                    lost += 1
                us.append(None if u is None else u.tolist())
                plant.step(u)  # the plant's flow map over [t_k, t_k+1), u = 0 if u_k never came
                x = plant.process.x
    finally:
        if realtime:
            set_realtime(False)
        os.killpg(echo.pid, signal.SIGINT)
        try:
            echo.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(echo.pid, signal.SIGKILL)
            echo.wait()
    same = None
    if not lost:
        from testbed.sim.batch import simulate_scenario

        same = bool(np.array_equal(np.array(us), simulate_scenario(sc, n_steps=n).u))
    shutil.rmtree(d, ignore_errors=True)
    a = np.array(lat) / 1e3
    return {"n": int(a.size), "lost": lost, "p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
            "max": float(a.max()), "u_equals_simulator": same, "_lat": a}


# ------------------------------------------------------------------ the live loop
def live_run(T: float, duration: float, deadline: float, realtime: bool, extra: list[str],
             env: dict | None = None) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-live-") as d:
        f = Path(d) / "bench.toml"
        f.write_text(SCENARIO.format(tag=f"{T:g}".replace(".", "_"), T=T, duration=duration, deadline=deadline))
        cmd = [sys.executable, "-m", "testbed.cli", "run", str(f), "--json", "--no-record"]  # as before recordings
        cmd += ["--realtime"] if realtime else []
        p = subprocess.run(cmd + extra, capture_output=True, text=True, timeout=duration + 600,
                           env=dict(os.environ, **(env or {})))
    try:
        s = json.loads(p.stdout)
    except json.JSONDecodeError:
        raise SystemExit(f"testbed run failed (exit {p.returncode}):\n{p.stderr[-3000:]}") from None
    s["_exit_code"] = p.returncode
    return s


def _p(d: dict | None, key: str) -> str:
    v = None if not d else d.get(key)
    return "   n/a" if v is None else f"{v:6.0f}"


#: the live loop's variants for A/B runs: name -> (extra flags of testbed run, environment).
_CPUS = sorted(os.sched_getaffinity(0))[:2]
VARIANTS = {
    "default": ([], {}),                                              # --topology auto: peer on one host
    "router": (["--topology", "router"], {}),                         # the router topology (the default before auto)
    "insecure": (["--insecure"], {}),                                 # no authentication, no access control
    "peer": (["--topology", "peer"], {}),                             # direct links (mutual TLS), no router
    "colocated": (["--colocate", "encoder"], {}),                     # the encoder in the plant's process
    "low-latency": (["--low-latency"], {}),                           # Zenoh's low-latency transport
    "rx-direct": (["--rx", "direct"], {}),                            # handlers on Zenoh's receive thread
    "rx-spin": (["--rx", "spin"], {}),                                # ... and a spin before the input is due
    "realtime": (["--realtime"], {}),                                 # SCHED_FIFO (the nodes and the router) at any T
    "no-realtime": (["--realtime", "off"], {}),                       # OFF: SCHED_FIFO by default below 10 ms
    "pinned": ([f for role, c in zip(("plant", "encoder", "attacker", "controller"), _CPUS * 2, strict=False)
                for f in ("--cpu", f"{role}={c}")], {}),                  # the nodes on the first two CPUs, in turn
    "exec": (["--spawn", "exec"], {}),                                # OFF: nodes forked from the launcher
    "separate-ack": (["--separate-ack"], {}),                         # OFF: the ack on the actuation message
}
#: ``--ab``: every change of the faster loop against the default, at each period
AB_SET = ("default", "no-realtime", "router", "exec", "separate-ack", "low-latency", "rx-direct", "rx-spin",
          "colocated", "insecure", "router+insecure", "router+colocated")


def variant(name: str) -> tuple[list[str], dict]:
    """Flags and environment of a variant; ``a+b`` combines two."""
    flags, env = [], {}
    for part in name.split("+"):
        if part not in VARIANTS:
            raise SystemExit(f"unknown variant {part!r}; known: {', '.join(VARIANTS)} (combine with +)")
        f, e = VARIANTS[part]
        flags += [x for x in f if not (x == "--insecure" and x in flags)]
        for k, v in e.items():
            env[k] = ",".join(filter(None, (env.get(k), v)))
    return flags, env


#: the goals (issue 24), as ratios to the floor measured in the same run
GOAL_P50_OVER_FLOOR = 1.2     # T = 0.1 s: sensor-to-actuator p50 <= 1.2 x the four-hop floor (2 x ping-pong RTT p50)
GOAL_MISSES_OVER_IDEAL = 2.0  # T = 2 ms: deadline misses <= 2 x the ideal four-hop loop's (``ideal_misses_per_10k``)


def goal_ratios(T: float, floor: dict, work: dict | None, s: dict, hops: str = "4 hops") -> dict:
    """The run's figures as ratios to the floor of the same invocation: p50 over the four-hop floor (2 x RTT
    p50) and over the floor with the work; deadline misses per 10,000 over the ideal loop's (``hops``), and
    over the ideal loop's with the work.  Which goal applies: T = 0.1 s the first, T = 2 ms the second,
    T = 1 ms both reported (``goals``).  A ratio is None where its floor is 0 or a figure is missing."""
    tm = s["timing"]
    p50 = tm["sensor_to_actuator_us"].get("p50")
    ran = bool(s["_exit_code"] == 0 and s.get("complete") and s["samples"] > 0)  # a run that never ran meets nothing
    per10k = tm["deadline_misses"] * 1e4 / s["samples"] if s["samples"] else None
    ideal = (floor.get("ideal_misses_per_10k") or {}).get(hops)
    ideal_w = (work or {}).get("ideal_misses_per_10k")

    def ratio(a, b):
        return None if a is None or not b else a / b

    r = {"p50_us": p50, "four_hop_floor_us": 2 * floor["p50"], "p50_over_floor": ratio(p50, 2 * floor["p50"]),
         "work_floor_us": (work or {}).get("p50"), "p50_over_work_floor": ratio(p50, (work or {}).get("p50")),
         "misses_per_10k": per10k, "ideal_misses_per_10k": ideal, "misses_over_ideal": ratio(per10k, ideal),
         "work_ideal_misses_per_10k": ideal_w, "misses_over_work_ideal": ratio(per10k, ideal_w)}
    goals = {}
    if abs(T - 0.1) < 1e-9 or abs(T - 0.001) < 1e-9:
        goals[f"p50 <= {GOAL_P50_OVER_FLOOR:g}x the four-hop floor"] = \
            ran and r["p50_over_floor"] is not None and r["p50_over_floor"] <= GOAL_P50_OVER_FLOOR
    if abs(T - 0.002) < 1e-9 or abs(T - 0.001) < 1e-9:
        goals[f"deadline misses <= {GOAL_MISSES_OVER_IDEAL:g}x the ideal four-hop loop's"] = \
            ran and per10k is not None and ideal is not None and per10k <= GOAL_MISSES_OVER_IDEAL * ideal
    r["goals"] = goals
    return r


def _x(v) -> str:
    return "n/a" if v is None else f"{v:.2f}x"


def report(T: float, floor: dict, s: dict, name: str = "default", work: dict | None = None) -> dict:
    tm = s["timing"]
    s2a = tm["sensor_to_actuator_us"]
    ns = s.get("node_summaries", {})
    sec = s.get("security") or {}
    print(f"\n=== T = {T:g} s, {name} (topology {sec.get('topology')}, {sec.get('transport')}): {s['samples']} samples "
          f"over {s['samples'] * T:g} s (deadline {s['deadline']:g} T, outcome {s['outcome']}, exit {s['_exit_code']})")
    print(f"  {'':28s}{'p50 us':>8s}{'p99 us':>8s}{'max us':>9s}")
    rows = [("sampling jitter", tm["sampling_jitter_us"]), ("sensor-to-actuator", s2a)]
    rows += [(f"  {k}", v) for k, v in tm["stages_us"].items()]
    rows += [("zenoh ping-pong RTT (floor)", floor)]
    if work:
        rows += [("four hops with the work", work)]
    for label, d in rows:
        print(f"  {label:28s}{_p(d, 'p50')}  {_p(d, 'p99')}  {_p(d, 'max')}")
    r50 = r99 = None
    if s2a.get("p50") is not None:
        r50 = s2a["p50"] / (2 * floor["p50"])
        r99 = s2a["p99"] / (2 * floor["p99"])
        print(f"  sensor-to-actuator / (2 x RTT floor): p50 {r50:.2f}x, p99 {r99:.2f}x"
              + (f"; / four hops with the work: p50 {s2a['p50'] / work['p50']:.2f}x" if work else ""))
    print(f"  deadline misses {tm['deadline_misses']} of {s['samples']}, overruns {tm['overruns']}, "
          f"samples lost {sum(v for v in s['theta'] if v)}, late symbols {s.get('late_symbols')}")
    print("  CPU share per node: " + ", ".join(f"{r} {ns[r].get('cpu_share', float('nan')):.0%}"
                                             for r in ("plant", "encoder", "attacker", "controller") if r in ns))
    flags, env = variant(name)
    g = goal_ratios(T, floor, work, s, "3 hops" if "--colocate" in flags else "4 hops")
    for what, met in g["goals"].items():
        print(f"  goal ({what}): {'MET' if met else 'NOT met'}")
    return {"T": T, "variant": name, "flags": flags, "env": env, "security": s.get("security"),
            "floor_rtt_us": floor, "work_floor_us": work, "timing": tm, "samples": s["samples"],
            "outcome": s["outcome"], "ratio_p50": r50, "ratio_p99": r99,
            "cpu_share": {r: ns[r].get("cpu_share") for r in ns},
            "lost": int(sum(v for v in s["theta"] if v)), "exit_code": s["_exit_code"],
            "ratios": {k: v for k, v in g.items() if k != "goals"}, "goals": g["goals"]}


def print_goals(T: float, floor: dict, work: dict | None, rows: list[dict]) -> None:
    """The goals of this period as ratios to the floor of this run, one line per variant (median over ``--reps``)."""
    print(f"\n  T = {T:g} s: goals against this run's floor (ping-pong RTT p50 {floor['p50']:.0f} us, four-hop floor "
          f"{2 * floor['p50']:.0f} us" + (f", four hops with the work {work['p50']:.0f} us" if work else "")
          + f"; ideal misses per 10,000: {(floor.get('ideal_misses_per_10k') or {}).get('4 hops')}"
          + (f", with the work {work.get('ideal_misses_per_10k')}" if work else "") + ")")
    for name in dict.fromkeys(r["variant"] for r in rows):
        rs = [r["ratios"] for r in rows if r["variant"] == name]

        def med(key, rs=rs):
            v = sorted(x[key] for x in rs if x[key] is not None)
            return v[len(v) // 2] if v else None

        parts = []
        if abs(T - 0.1) < 1e-9 or abs(T - 0.001) < 1e-9:
            parts.append(f"p50 / four-hop floor {_x(med('p50_over_floor'))} (goal <= {GOAL_P50_OVER_FLOOR:g}x), "
                         f"/ with the work {_x(med('p50_over_work_floor'))}")
        if abs(T - 0.002) < 1e-9 or abs(T - 0.001) < 1e-9:
            m = med("misses_per_10k")
            each = [x["misses_per_10k"] for x in rs if x["misses_per_10k"] is not None]
            spread = f" (runs: {', '.join(f'{v:.0f}' for v in each)})" if len(each) > 1 else ""
            parts.append(f"misses per 10,000 {'n/a' if m is None else f'{m:.0f}'}{spread} / ideal "
                         f"{_x(med('misses_over_ideal'))} (goal <= {GOAL_MISSES_OVER_IDEAL:g}x), "
                         f"/ ideal with the work {_x(med('misses_over_work_ideal'))}")
        if not parts:
            parts.append(f"p50 / four-hop floor {_x(med('p50_over_floor'))}, / with the work "
                         f"{_x(med('p50_over_work_floor'))}")
        print(f"    {name:10s} " + "; ".join(parts))


def table(runs: list[dict]) -> str:
    """The Markdown table of docs/benchmarks.md from ``--json`` output."""
    def us(d, key):
        v = (d or {}).get(key)
        return "n/a" if v is None else (f"{v / 1000:.2f} ms" if v >= 1000 else f"{v:.0f} us")

    lines = ["| T | variant | sensor-to-actuator p50 / p99 | vs default p50 | stages p50 (enc / proxy / ctl / plant) "
             "| jitter p99 | misses | ping-pong RTT p50 |", "|---|---|---|---|---|---|---|---|"]
    base = {}
    for r in runs:  # against the default of the same repetition (``--reps``)
        if r["variant"] == "default":
            base[r["T"], r.get("rep", 0)] = r["timing"]["sensor_to_actuator_us"]["p50"]
    for r in runs:
        tm = r["timing"]
        s2a = tm["sensor_to_actuator_us"]
        st = tm["stages_us"]
        b = base.get((r["T"], r.get("rep", 0)))
        ratio = f"{s2a['p50'] / b:.2f}x" if b and s2a.get("p50") and r["variant"] != "default" else ""
        stages = " / ".join(f"{(st[k] or {}).get('p50') or 0:.0f}" for k in ("encoder", "proxy", "controller", "plant"))
        T = f"{r['T'] * 1000:g} ms" if r["T"] < 0.1 else f"{r['T']:g} s"
        lines.append(f"| {T} | {r['variant']} | {us(s2a, 'p50')} / {us(s2a, 'p99')} | {ratio} | {stages} us | "
                     f"{us(tm['sampling_jitter_us'], 'p99')} | {tm['deadline_misses']:,} of {r['samples']:,} | "
                     f"{us(r['floor_rtt_us'], 'p50')} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of live loop per period")
    ap.add_argument("--periods", default="0.1,0.002,0.001", help="comma-separated sample periods (s)")
    ap.add_argument("--pingpong-seconds", type=float, default=10.0)
    ap.add_argument("--deadline", type=float, help="[run] deadline (default 0.5, 0.8 at T <= 2 ms)")
    ap.add_argument("--realtime", action="store_true", help="nodes and ping-pong under SCHED_FIFO")
    ap.add_argument("--json", metavar="FILE", help="write the figures as JSON")
    ap.add_argument("--variants", default="default,router",
                    help=f"comma-separated live-loop variants, run one after the other at each period "
                         f"({', '.join(VARIANTS)}; combine with +)")
    ap.add_argument("--auth", action="store_true", help="--variants default,insecure: the cost of authentication")
    ap.add_argument("--ab", action="store_true", help=f"--variants {','.join(AB_SET)}: the A/B of every change")
    ap.add_argument("--reps", type=int, default=1,
                    help="run the variants round-robin this many times (A/B on a busy machine)")
    ap.add_argument("--table", metavar="FILE.json", help="print the Markdown table of a --json file and exit")
    ap.add_argument("--no-work-floor", action="store_true",
                    help="skip the floor with the work (the four hops with the nodes' per-sample work)")
    ap.add_argument("--echo", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--echo-seconds", type=float, default=60.0, help=argparse.SUPPRESS)
    ap.add_argument("--echo-work", help=argparse.SUPPRESS)
    ap.add_argument("--echo-n", type=int, help=argparse.SUPPRESS)
    args, extra = ap.parse_known_args()
    if args.echo and args.echo_work:
        echo_work_main(args.echo, args.echo_seconds, args.realtime, args.echo_work, args.echo_n)
        return 0
    if args.echo:
        echo_main(args.echo, args.echo_seconds, args.realtime)
        return 0
    if args.table:
        print(table(json.loads(Path(args.table).read_text())))
        return 0
    out = []
    print(f"host: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}, "
          f"{'SCHED_FIFO' if args.realtime else 'normal scheduling'}")
    variants = ["default", "insecure"] if args.auth else list(AB_SET) if args.ab else args.variants.split(",")
    for v in variants:
        variant(v)  # unknown names: one clear line now
    for T in (float(t) for t in args.periods.split(",")):
        deadline = args.deadline if args.deadline is not None else (0.8 if T <= 0.002 else 0.5)
        floor = ping_pong(T, args.pingpong_seconds, args.realtime, deadline * T)
        im = floor.get("ideal_misses_per_10k")
        if im:
            print(f"\nT = {T:g} s: ping-pong RTT p50 {floor['p50']:.0f} us, p99 {floor['p99']:.0f} us; an ideal loop "
                  f"whose hops each took half an RTT would miss {im['4 hops']:g} of 10,000 deadlines ({deadline:g} T) "
                  f"with four hops, {im['3 hops']:g} with three")
        work = None
        if not args.no_work_floor:
            work = work_ping_pong(T, args.pingpong_seconds, args.realtime, deadline * T)
            print(f"T = {T:g} s: four hops with the work p50 {work['p50']:.0f} us, p99 {work['p99']:.0f} us "
                  f"(bare: 2 x RTT p50 {2 * floor['p50']:.0f} us); its u_k equal the simulator's: "
                  f"{work['u_equals_simulator']}; an ideal loop of those would miss {work.get('ideal_misses_per_10k')} "
                  f"of 10,000 deadlines")
        extra_T = list(extra) + (["--loss-fraction", "0.95"] if T <= 0.002 and "--loss-fraction" not in extra else [])
        rows = []
        for rep in range(args.reps):
            for v in variants:
                flags, env = variant(v)
                s = live_run(T, args.duration, deadline, args.realtime, extra_T + flags, env)
                row = report(T, floor, s, v, work)
                row["rep"] = rep
                rows.append(row)
        out.extend(rows)
        print_goals(T, floor, work, rows)
        if args.json:  # after every period: a later failure keeps what was measured
            Path(args.json).write_text(json.dumps(out, indent=1))
        if len(variants) > 1:
            def med(name):
                v = sorted(r["timing"]["sensor_to_actuator_us"]["p50"] for r in rows  # noqa: B023 - called in this iteration
                           if r["variant"] == name and r["timing"]["sensor_to_actuator_us"]["p50"])
                return v[len(v) // 2] if v else None

            base = med(variants[0])
            print(f"\n  T = {T:g} s, sensor-to-actuator p50 against {variants[0]}"
                  + (f" (median of {args.reps})" if args.reps > 1 else "") + ": " + ", ".join(
                      f"{v} {med(v) / base:.2f}x" for v in variants[1:] if base and med(v)))
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
