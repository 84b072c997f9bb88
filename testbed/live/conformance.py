"""``testbed conformance``: run a scenario live with one role played by a command from outside, then check
that node requirement by requirement against the spec (docs/protocol.md) and the simulator.

The run is ``testbed run SCENARIO --external ROLE --record-loop on`` (a subprocess); the command is started
with ``TESTBED_JOIN`` set once the run has written its join file.  What is judged comes from the run's
recording (every message of the control path, decoded by the recorder, and every message it could not
decode), its summary, and the command's exit.  The model: ideal timing on a machine that does not stall
the testbed's own nodes; a run whose own nodes report a stall (``stalled``) is run once more, and if it
stalls again the requirements that depend on timing are ``inconclusive``, not failed.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from ..record.tracereader import read_recording_trace
from ..wire import join, transport
from ..wire.session import SessionOptions
from . import adverse
from .external import ANNOUNCE

if TYPE_CHECKING:
    from ..scenario import Scenario

#: the per-sample keys of a run that must equal the simulator's bit for bit (as the bit-exact tests compare)
BIT_EXACT_KEYS = ("symbols", "theta", "E", "E_dec", "xi", "q", "x", "u", "saturated_at", "x_final")
#: the requirements, in the order they are reported
REQUIREMENTS = ("joined_in_time", "messages_well_formed", "sample_indices", "telemetry_agrees_with_messages",
                "equals_simulator", "acks_and_deadlines", "clean_stop")
#: ROLE plant: a device's judgement, reported after equals_simulator and required unless --bit-exact (then
#: equals_simulator is required instead): the loop re-run on the plant's reported states equals the run bit
#: for bit, and the plant's steps follow the scenario's model within --plant-tolerance
DEVICE = ("loop_equals_replay", "plant_follows_model")
#: ``--plant-tolerance``'s default: the largest max_k ||x_k+1 - phi_T(x_k, u_k)||_inf plant_follows_model passes
PLANT_TOLERANCE = 1e-6
#: ... and, unless --no-adverse, the adverse cases (``testbed.live.adverse``)
ADVERSE = tuple(f"adverse_{case}" for case, _ in adverse.CASES)
#: per-sample keys: where the run first left the simulator
PER_SAMPLE = ("symbols", "theta", "E", "E_dec", "xi", "q", "x", "u")
#: a node's counters (its NodeSummary) shown as the adverse cases' evidence
COUNTERS = ("malformed", "late_u", "stale_sensor", "stale_acks", "late", "future")
#: the requirements a stall of the testbed's own nodes can break (inconclusive after two stalled runs)
TIMING = ("equals_simulator", "acks_and_deadlines", "plant_follows_model")
#: the requirement a device fault of the node breaks (``testbed.live.devicefaults``; the fault's kind -> requirement)
DEVICE_FAULT_BREAKS = {"state_nonfinite": "messages_well_formed", "state_wrong_length": "messages_well_formed",
                       "sample_late": "acks_and_deadlines", "no_stop": "clean_stop", "lost": "clean_stop"}
#: the control-path keys (after the prefix) each role publishes
PUBLISHES = {"plant": ("loop/sensor",), "encoder": ("loop/symbol/tx",), "attacker": ("loop/symbol/rx", "loop/ack/rx"),
             "controller": ("loop/actuation", "loop/ack/tx")}
PASS, FAIL, INCONCLUSIVE = "pass", "fail", "inconclusive"
STOP_GRACE_S = 5.0  # the command must exit this long after the run's end at the latest
NODE_DEAD_S = 10.0  # a command that failed: the run is interrupted this long after


@dataclass
class ExternalRun:
    """One run with an external node: the launcher's summary and what the command did."""

    rc: int | None = None
    summary: dict | None = None
    stderr: str = ""
    join_path: str | None = None
    join_mode: int | None = None
    join_removed: bool | None = None
    join_data: dict | None = None            # the join file as the command read it
    command_rc: int | None = None
    command_stopped_s: float | None = None   # after the run ended (None: it did not stop by itself)
    command_log: str = ""
    recording: str | None = None
    notes: list = field(default_factory=list)
    fed: dict | None = None                  # the adverse cases fed (None: not asked)
    feed_error: str | None = None


def _reader(stream, sink: list, found: dict, ev: threading.Event, prefix: str) -> None:
    for line in stream:
        sink.append(line)
        if "path" not in found and line.startswith(prefix):
            found["path"] = line.rstrip("\n")[len(prefix):]
            ev.set()
    ev.set()


def _stop_group(p: subprocess.Popen) -> None:
    for sig in (signal.SIGINT, signal.SIGKILL):
        if p.poll() is not None:
            return
        try:
            os.killpg(p.pid, sig)
        except ProcessLookupError:
            return
        try:
            p.wait(3.0)
        except subprocess.TimeoutExpired:
            pass


def feedable(session: SessionOptions) -> str | None:
    """Why the adverse cases cannot be fed in the run's session (``testbed run``'s session: ``SessionOptions.of("run")``;
    None: they can): the feeding peer joins with a role's certificate (``--tls-dir``, or one made for the run), or
    unauthenticated (``--insecure``)."""
    listen = session.listen[0] if session.listen else None
    if session.secret_file and not session.insecure:
        return ("--secret-file: the adverse cases are fed by a peer holding a role's certificate; give "
                "--tls-dir DIR instead, or --no-adverse")
    if listen and not listen.startswith("tls/" if not session.insecure else "tcp/"):
        return (f"--listen {listen}: the adverse cases' feeding peer connects to a "
                f"{'tcp' if session.insecure else 'tls'}/HOST:PORT endpoint; give one, or --no-adverse")
    return None


def run_external(role: str, scenario: str, command: list[str], *, run_id: str, folder: Path,
                 flags: Sequence[str] = (),
                 timeout: float = 300.0, startup_timeout: float = 120.0, feed: bool = False,
                 session: SessionOptions | None = None) -> ExternalRun:
    """``testbed run SCENARIO --external ROLE`` with ``command`` as the ROLE (``TESTBED_JOIN`` set), to the end,
    in ``session``; ``feed``: the adverse cases fed to it (through the run's endpoint, with its TLS folder: one
    made for the run when ``session`` names none)."""
    session = dataclasses.replace(session or SessionOptions.of("run"), run_id=run_id)
    folder.mkdir(parents=True, exist_ok=True)
    recording = str(folder / f"{run_id}.mcap")
    out = ExternalRun(recording=recording)
    feeder = None
    if feed:
        why = feedable(session)
        if why:
            raise ValueError(why)
        tls = None if session.insecure else (session.tls_dir or
                                             str(transport.TlsCredentials.new(folder / f"{run_id}-tls").folder))
        listen = session.listen[0] if session.listen else \
            f"{'tcp' if tls is None else 'tls'}/127.0.0.1:{transport.free_port()}"
        session = dataclasses.replace(session, tls_dir=tls, listen=(listen,))
        feeder = adverse.Feeder(role, run_id, tls, listen, mode="client" if session.topology == "router" else "peer",
                                low_latency=session.low_latency)
    flags = (*flags, *session.argv("run"))  # testbed run's own flags: the session as the launcher takes it
    cmd = [sys.executable, "-P", "-m", "testbed.cli", "run", scenario, "--external", role, "--json",
           "--run-dir", str(folder / run_id), "--out", recording, "--force", "--record-loop", "on",
           "--startup-timeout", str(startup_timeout), *flags]
    p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    err: list[str] = []
    found: dict = {}
    announced = threading.Event()
    prefix = ANNOUNCE.format(role=role, path="")
    t_err = threading.Thread(target=_reader, args=(p.stderr, err, found, announced, prefix), daemon=True)
    t_err.start()
    stdout: list[str] = []
    assert p.stdout is not None  # a pipe (Popen above)
    out_pipe = p.stdout
    t_out = threading.Thread(target=lambda: stdout.append(out_pipe.read()), daemon=True)
    t_out.start()
    node = None
    log_path = folder / f"{run_id}-{role}.log"
    try:
        announced.wait(timeout)
        out.join_path = found.get("path")
        if out.join_path is not None and feeder is not None:
            feeder.start()  # before the node: it must see the node's first inputs
        if out.join_path is not None:
            try:
                out.join_mode = os.stat(out.join_path).st_mode & 0o777
                out.join_data = join.read(out.join_path).data
            except (OSError, ValueError) as e:
                out.notes.append(f"join file: {e}")
            with open(log_path, "wb") as log:
                try:
                    node = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                            start_new_session=True, env={**os.environ, join.ENV: out.join_path})
                except OSError as e:
                    out.notes.append(f"the command did not start: {e}")
        end, dead_since = time.monotonic() + timeout, None
        while p.poll() is None:
            if time.monotonic() > end:
                out.notes.append(f"the run did not end in {timeout:g} s")
                _stop_group(p)
                break
            if node is not None and node.poll() not in (None, 0):
                dead_since = dead_since or time.monotonic()
                if time.monotonic() - dead_since > NODE_DEAD_S:  # it failed: the run cannot go on without it
                    out.notes.append(f"the command exited with status {node.returncode} while the run went on; "
                                     "the run was interrupted")
                    _stop_group(p)
                    break
            time.sleep(0.05)
        t_end = time.monotonic()
        if node is not None:
            try:
                out.command_rc = node.wait(max(0.0, STOP_GRACE_S - (time.monotonic() - t_end)))
                out.command_stopped_s = round(time.monotonic() - t_end, 3)
            except subprocess.TimeoutExpired:
                _stop_group(node)
                out.command_rc = node.returncode
    finally:
        _stop_group(p)
        if node is not None:
            _stop_group(node)
        if feeder is not None:
            feeder.close()
            out.fed, out.feed_error = dict(feeder.fed), feeder.error
    t_out.join(10)
    t_err.join(10)
    out.rc = p.returncode
    out.stderr = "".join(err)
    if out.join_path is not None:
        out.join_removed = not os.path.exists(out.join_path)
    try:
        out.command_log = log_path.read_text(errors="replace")
    except OSError:
        pass
    try:
        out.summary = json.loads(stdout[0]) if stdout and stdout[0].strip() else None
    except json.JSONDecodeError:
        out.notes.append("the run printed no JSON summary")
    return out


#: who reports each stall criterion: what the external node itself reports is not the testbed's own stall
#: (it may be the node's fault, or the adverse cases' doing: a late sensor is a ``stale_sensor``)
REPORTED_BY = {"stale_sensor": "encoder", "ack_missing": "encoder", "future_sensor": "encoder",
               "late_symbols": "controller", "superseded": "controller", "future_symbol": "controller",
               "overruns": "plant", "late_for_schedule": "plant", "future_actuation": "plant"}


def stalled(summary: dict, external: str | None = None) -> dict | None:
    """The timing faults the testbed's own run reports (a machine that stalled a node), or None: deadline
    misses, overruns, sensor samples out of order, an ack that missed the encoder's grace window, late or
    superseded symbols, genuine messages taken for ones from the future (the tests' rerun policy); without
    those the ``external`` role reports itself (``REPORTED_BY``)."""
    tm = summary.get("timing") or {}
    ev = summary.get("events") or {}
    enc = (summary.get("node_summaries") or {}).get("encoder") or {}
    stall = {"deadline_misses": tm.get("deadline_misses"), "overruns": tm.get("overruns"),
             "stale_sensor": enc.get("stale_sensor"), "late_for_schedule": tm.get("late_for_schedule"),
             "late_symbols": summary.get("late_symbols"),
             "superseded": (summary.get("loss_reasons") or {}).get("superseded")}
    if not summary.get("ack_via_attacker"):
        stall["ack_missing"] = ev.get("ack_missing")
    stall.update({k: ev.get(k) for k in ("future_sensor", "future_symbol", "future_actuation")})
    stall = {k: v for k, v in stall.items() if v and (external is None or REPORTED_BY.get(k) != external)}
    return stall or None


def own_report(summary: dict | None, external: str) -> dict | None:
    """The timing account of the testbed's own nodes in a run's summary (the keys its stall criterion reads),
    without what the ``external`` role reports of itself: each run's ``report`` in the JSON."""
    if not summary:
        return None
    drop = {k for k, who in REPORTED_BY.items() if who == external}
    tm = summary.get("timing") or {}
    ns = summary.get("node_summaries") or {}
    return {"timing": {k: tm.get(k) for k in ("deadline_misses", "overruns", "late_for_schedule", "sampling_jitter_us")
                       if k not in drop},
            "events": {k: v for k, v in (summary.get("events") or {}).items() if k not in drop},
            "node_summaries": {r: {"stale_sensor": v.get("stale_sensor")} for r, v in ns.items()
                               if r != external and isinstance(v, dict)},
            "late_symbols": None if "late_symbols" in drop else summary.get("late_symbols"),
            "loss_reasons": {} if "superseded" in drop else summary.get("loss_reasons") or {},
            "ack_via_attacker": summary.get("ack_via_attacker"),
            "deadline_missed_at": summary.get("deadline_missed_at"), "withheld_at": summary.get("withheld_at")}


# ============================================================================ the checks
def _verdict(name: str, status: str, detail: str, required: bool = True) -> dict:
    return {"name": name, "required": required, "passed": status == PASS, "status": status, "detail": detail}


def names(role: str, adverse_cases: bool) -> tuple[str, ...]:
    """The requirements reported for ``role``, in order (``adverse_cases``: the cases were fed)."""
    i = REQUIREMENTS.index("equals_simulator") + 1
    own = REQUIREMENTS[:i] + (DEVICE if role == "plant" else ()) + REQUIREMENTS[i:]
    return own + (ADVERSE if adverse_cases else ())


def first_difference(live: dict, sim: dict) -> tuple[int | None, list[str]]:
    """Where a run's summary first differs from the simulator's (the keys of ``BIT_EXACT_KEYS``): the first
    sample at which any per-sample quantity differs and which do there; (None, the keys that differ) when no
    per-sample one does (saturated_at, x_final); (None, []) when nothing does."""
    firsts = {}
    for c in PER_SAMPLE:
        a, b = live.get(c), sim.get(c)
        if isinstance(a, list) and isinstance(b, list):
            k = next((i for i, (x, y) in enumerate(zip(a, b)) if x != y), None)
            if k is None and len(a) != len(b):
                k = min(len(a), len(b))
            if k is not None:
                firsts[c] = k
        elif a != b:
            firsts[c] = 0
    if firsts:
        k = min(firsts.values())
        return k, [c for c in PER_SAMPLE if firsts.get(c) == k]
    return None, [c for c in BIT_EXACT_KEYS if live.get(c) != sim.get(c)]


def _at(v, k):
    return v[k] if isinstance(v, list) and k < len(v) else None


def device_verdicts(replay: dict | None, tolerance: float, *, required: bool = True,
                    error: str | None = None, stall_again: dict | None = None) -> list[dict]:
    """ROLE plant's ``loop_equals_replay`` and ``plant_follows_model`` from ``replay``, the recording's re-run on
    the recorded plant (``testbed.runs.resimulate.resimulation(run, plant="recorded")``: its ``loop_identical``,
    ``loop_first_divergence``, ``loop_differs_in`` and ``plant_model_error`` as they are); ``error``: why there
    is none.  ``stall_again`` (the run stalled twice): a plant that does not follow the model is inconclusive
    (a stalled loop may have driven it where no healthy run goes: an escaped state, a clamped input); the
    replay replays the recorded timing faults, so ``loop_equals_replay`` is judged as usual."""
    if replay is None:
        why = f"no re-run of the recording: {error or 'none made'}"
        return [_verdict(n, FAIL, why, required) for n in DEVICE]
    n = replay.get("resimulated")
    if replay["loop_identical"]:
        loop = _verdict("loop_equals_replay", PASS, f"the testbed's nodes re-run on the plant's reported states equal "
                                                    f"the run bit for bit ({n} samples): the loop trusted the plant's "
                                                    "numbers and did what the method says", required)
    else:
        which = ", ".join(replay.get("loop_differs_in") or []) or "the re-run stopped"
        loop = _verdict("loop_equals_replay", FAIL, f"the testbed's nodes re-run on the plant's reported states differ "
                                                    f"from the run at sample {replay['loop_first_divergence']} "
                                                    f"({which})", required)
    pm = replay.get("plant_model_error")
    if pm is None:
        model = _verdict("plant_follows_model", FAIL, "no step of the plant to compare with the model (no two "
                                                      "consecutive records, or a model without equations: an FMU; "
                                                      "--bit-exact judges such a plant)", required)
    else:
        ok = pm["max"] <= tolerance
        model = _verdict("plant_follows_model", PASS if ok else INCONCLUSIVE if stall_again else FAIL,
                         f"max_k ||x_k+1 - phi_T(x_k, u_k)||_inf = {pm['max']:.3g} at sample {pm['at']} "
                         f"{'<=' if ok else '>'} tolerance {tolerance:g} (mean {pm['mean']:.3g})"
                         + (f" (the run stalled twice: {stall_again})" if stall_again and not ok else ""), required)
    return [loop, model]


def run_scenario(jd: dict) -> Scenario:
    """The run's scenario with the run's options (the seed it drew included), from its join file."""
    from .. import scenario as scn
    from ..nodes.options import RunOptions

    opts = RunOptions.of_join(jd["run_options"])
    s = jd["scenario"]
    return scn.loads(s["toml"], name=s["name"], base_dir=s["base_dir"], overrides=opts.overrides(),
                     read_recording_trace=read_recording_trace)


def simulated(sc: Scenario) -> dict:
    """``testbed simulate --json`` of scenario ``sc`` (the same per-sample simulator)."""
    from ..sim.batch import summarize
    from ..sim.trajectory import simulate_scenario

    return json.loads(json.dumps(summarize(sc, simulate_scenario(sc))))


def check_run(role: str, scenario: str, r: ExternalRun, *, stall_again: dict | None = None, bit_exact: bool = False,
              plant_tolerance: float = PLANT_TOLERANCE,
              replay: Callable[[str], dict] | None = None) -> list[dict]:
    """Every requirement of ``names(role, ...)`` judged on run ``r`` (``stall_again``: the run stalled twice).

    ``replay(path) -> dict``: the recording's re-run on the recorded plant (``resimulation(run,
    plant="recorded")``, which the commands' layer supplies); ROLE plant's ``DEVICE`` requirements and the
    loop's nodes' adverse cases read it.  ROLE plant: ``equals_simulator`` is required only with ``bit_exact``,
    the ``DEVICE`` requirements only without it (``plant_tolerance``: plant_follows_model's)."""
    out = []
    s = r.summary or {}
    rec = None
    if r.recording and os.path.exists(r.recording):
        from ..record.reader import read

        try:
            rec = read(r.recording)
        except (OSError, ValueError) as e:
            r.notes.append(f"recording unreadable: {e}")
    started = bool(s.get("samples")) and rec is not None and rec.start is not None and r.join_data is not None
    # 1. joined in time
    if r.join_path is None:
        out.append(_verdict("joined_in_time", FAIL, f"the run wrote no join file: {r.stderr.strip()[-300:]}"))
    elif not started:
        faults = "; ".join(f"{f.get('kind')}: {f.get('why')}" for f in s.get("faults", []))
        out.append(_verdict("joined_in_time", FAIL, f"the run never started (outcome {s.get('outcome')!r}; {faults}; "
                                                    f"the command's last line: {_last(r.command_log)!r})"))
    else:
        out.append(_verdict("joined_in_time", PASS, f"the external {role} joined and the run started "
                                                   f"(join file mode {r.join_mode:o})"))
    if not started:
        for name in names(role, r.fed is not None)[1:]:
            out.append(_verdict(name, FAIL, "the run never started", _required(role, name, bit_exact)))
        return out
    assert rec is not None and rec.start is not None and r.join_data is not None  # started
    N, T = rec.start.n_steps, rec.start.T_ns
    mine = {"/" + k for k in PUBLISHES[role]}
    # 2. well formed
    bad = [m for m in rec.malformed if m.get("key", "").split(f"{transport.ROOT}/{s['run_id']}/", 1)[-1]
           in {*PUBLISHES[role], f"telemetry/{role}", f"events/{role}", f"summary/{role}"}]
    ours = (r.fed or {}).get("invalid")  # the adverse case's 11-byte header, rejected by every reader of that key
    rejected = [e for e in rec.events if e.node != role and e.kind in ("malformed", "invalid_payload")
                and not (ours and e.kind == "malformed" and e.k == -1 and "header of 11 bytes" in e.detail)]
    if bad:
        out.append(_verdict("messages_well_formed", FAIL, f"{len(bad)} malformed; the first: {bad[0]['key']}: "
                                                          f"{bad[0]['error']}"))
    elif rejected:
        ev = rejected[0]
        out.append(_verdict("messages_well_formed", FAIL, f"the {ev.node} rejected a message ({ev.kind}) at sample "
                                                          f"{ev.k}: {ev.detail}"))
    else:
        n = sum(len(rec.loop.get(t, [])) for t in mine)
        out.append(_verdict("messages_well_formed", PASS, f"{n} control messages and {len(rec.telemetry.get(role, {}))} "
                                                          "telemetry records decoded; no receiver rejected one"))
    # 3. header and sample indices
    out.append(_indices(role, rec, mine, N, T))
    # 4. telemetry against the messages
    out.append(_agrees(role, rec))
    # 5. equal to the simulator
    sc = run_scenario(r.join_data)
    sim = simulated(sc)
    first, which = first_difference(s, sim)
    req = _required(role, "equals_simulator", bit_exact)
    if not which:
        out.append(_verdict("equals_simulator", PASS, f"{', '.join(BIT_EXACT_KEYS)} equal to testbed simulate "
                                                      f"bit for bit ({s.get('samples')} samples)", req))
    else:
        if first is None:
            where = f"{', '.join(which)} differ" + "".join(f"; {c}: live {s.get(c)!r}, simulator {sim.get(c)!r}"
                                                             for c in which[:2])
        else:
            where = f"first differs at sample {first}, in {', '.join(which)}" + "".join(
                f"; {c}: live {_at(s.get(c), first)!r}, simulator {_at(sim.get(c), first)!r}" for c in which[:3])
        out.append(_verdict("equals_simulator", INCONCLUSIVE if stall_again else FAIL,
                            where + (f" (the run stalled twice: {stall_again})" if stall_again else ""), req))
    # 5b. a plant as a device: the loop on its reported states, and its steps against the model
    rep, rep_error = None, None
    if replay is not None and (role == "plant" or r.fed is not None):
        try:
            assert r.recording is not None  # run_external names it
            rep = replay(r.recording)
        except Exception as e:  # noqa: BLE001 - reported as the requirement's detail
            rep_error = f"{type(e).__name__}: {e}"
    if role == "plant":
        out += device_verdicts(rep, plant_tolerance, required=not bit_exact, stall_again=stall_again,
                               error=rep_error or (None if replay else "no replay given"))
    # 6. acks and deadlines
    out.append(_acks(role, rec, s, N, T, sc.run.deadline, stall_again))
    # 7. clean stop
    out.append(_stop(role, rec, r, s))
    # 8. the adverse cases, each from what the node did with the message (``testbed.live.adverse``)
    if r.fed is not None:
        ns = (s.get("node_summaries") or {}).get(role) or {}
        counts = {c: ns.get(c) for c in COUNTERS if isinstance(ns.get(c), int)}
        if role == "plant":
            acted = {k: (tuple(t.u), t.flags) for k, t in rec.telemetry.get("plant", {}).items()}
            sent = {k: tuple(t.u) for k, t in rec.telemetry.get("controller", {}).items()}
            judge = adverse.plant_judge(acted, sent, N, sc.controller.u_max)
        elif rep is None:
            def judge(case, f, why=rep_error or "none made"):
                return INCONCLUSIVE, f"no replay of the recording to judge it by: {why}"
        else:
            judge = adverse.loop_judge(rep["loop_first_divergence"], rep.get("loop_differs_in") or [],
                                       _repeated(role, rec), OBSERVED[role])
        out += adverse.verdicts(r.fed, r.feed_error, judge, node_counts=counts)
    for f in s.get("faults", []):  # a device fault of the node fails the requirement it breaks, naming it (one the
        # run's stall left inconclusive stays so: a stalled machine makes a device late too)
        q = next((q for q in out if f.get("node") == role and q["name"] == DEVICE_FAULT_BREAKS.get(f.get("kind"))), None)
        if q is not None and q["status"] == PASS:
            q.update(_verdict(q["name"], FAIL, f"device fault {f['kind']} at sample {f.get('at_sample')}: {f.get('why')}",
                              q["required"]))
    return out


#: what each node of the loop is judged by in the adverse cases (``adverse.loop_judge``)
OBSERVED = {"encoder": "the symbol it sent (and its xi_k, E_k, q_k)",
            "controller": "the theta_k and u_k it sent (and its E_k, xi_k, q_k)",
            "attacker": "what the controller received through it"}


def _repeated(role: str, rec) -> dict:
    """The samples for which the node sent its control message more than once (the encoder's symbol, the
    controller's actuation; an attacker may forward repeats): k -> what."""
    topic = {"encoder": "/loop/symbol/tx", "controller": "/loop/actuation"}.get(role)
    if topic is None:
        return {}
    seen: dict = {}
    for m in rec.loop.get(topic, []):
        seen[m.k] = seen.get(m.k, 0) + 1
    return {k: f"it sent {n} messages on {topic[1:]} for sample {k}" for k, n in seen.items() if n > 1}


def _required(role: str, name: str, bit_exact: bool) -> bool:
    """ROLE plant: equals_simulator only with --bit-exact, the device's requirements only without it."""
    if role != "plant":
        return True
    if name == "equals_simulator":
        return bit_exact
    return not (bit_exact and name in DEVICE)


def _last(text: str) -> str:
    lines = text.strip().splitlines()
    return lines[-1] if lines else ""


def _indices(role, rec, mine, N, T) -> dict:
    tol = 2_000_000  # CLOCK_TOLERANCE_NS
    for topic in sorted(mine):
        ks = [m.k for m in rec.loop.get(topic, [])]
        for i, m in enumerate(rec.loop.get(topic, [])):
            if not 0 <= m.k < N:
                return _verdict("sample_indices", FAIL, f"{topic}: header k = {m.k} outside 0 .. {N - 1}")
            if i and m.k <= ks[i - 1] and role != "attacker":  # an attacker forwards late and repeated symbols
                return _verdict("sample_indices", FAIL, f"{topic}: header k = {m.k} after k = {ks[i - 1]} (not in "
                                                        "order, or twice)")
            if m.stamp_ns < m.k * T - tol:
                return _verdict("sample_indices", FAIL, f"{topic}: sample {m.k}'s header stamp {m.stamp_ns} ns is "
                                                        f"before t_k = {m.k * T} ns")
        if topic == "/loop/sensor" and ks != list(range(N)):
            miss = sorted(set(range(N)) - set(ks))
            return _verdict("sample_indices", FAIL, f"/loop/sensor: samples {miss[:5]} never sent")
        if topic == "/loop/actuation" and ks != list(range(N)):
            miss = sorted(set(range(N)) - set(ks))
            return _verdict("sample_indices", FAIL, f"/loop/actuation: no actuation for samples {miss[:5]}")
    tk = sorted(rec.telemetry.get(role, {}))
    if role in ("plant", "controller") and tk != list(range(N)):
        return _verdict("sample_indices", FAIL, f"telemetry/{role}: samples {sorted(set(range(N)) - set(tk))[:5]} "
                                                "have no record")
    if role == "plant" and (rec.plant_final is None or rec.plant_final.k != N):
        return _verdict("sample_indices", FAIL, f"telemetry/plant: no final record k = {N}")
    if rec.duplicates and role != "attacker":  # one record per symbol received (the spec), repeats too
        return _verdict("sample_indices", FAIL, f"{rec.duplicates} telemetry records of a sample already recorded")
    if role == "attacker":
        return _verdict("sample_indices", PASS, f"headers k within 0 .. {N - 1}, stamps at or after t_k; telemetry "
                                                f"k = 0 .. {N - 1} at most once each")
    return _verdict("sample_indices", PASS, f"headers k = 0 .. {N - 1} in order with stamps at or after t_k; "
                                            f"telemetry k = 0 .. {N - 1} once each")


def _agrees(role, rec) -> dict:
    tel = rec.telemetry.get(role, {})
    name = "telemetry_agrees_with_messages"
    if role == "plant":
        for m in rec.loop.get("/loop/sensor", []):
            t = tel.get(m.k)
            if t is not None and tuple(t.x) != tuple(m.x):
                return _verdict(name, FAIL, f"sample {m.k}: loop/sensor carries x = {list(m.x)}, the plant's "
                                            f"telemetry x_k = {list(t.x)}")
        return _verdict(name, PASS, "every loop/sensor x equals the telemetry's x_k")
    if role == "controller":
        for m in rec.loop.get("/loop/actuation", []):
            t = tel.get(m.k)
            if t is not None and (tuple(t.u) != tuple(m.u) or t.theta != m.theta):
                return _verdict(name, FAIL, f"sample {m.k}: loop/actuation carries theta {m.theta}, u = {list(m.u)}; "
                                            f"the telemetry theta {t.theta}, u = {list(t.u)}")
        return _verdict(name, PASS, "every loop/actuation theta_k, u_k equals the telemetry's")
    if role == "encoder":
        sent = {m.k: int.from_bytes(m.data, "big") for m in rec.loop.get("/loop/symbol/tx", [])}
        for k, t in tel.items():
            want = sent.get(k, -1)
            if t.symbol != want:
                return _verdict(name, FAIL, f"sample {k}: telemetry symbol {t.symbol}, loop/symbol/tx carried "
                                            f"{'none' if want < 0 else want}")
        return _verdict(name, PASS, "every symbol sent equals the telemetry's, and none was sent unrecorded")
    fwd = {m.k for m in rec.loop.get("/loop/symbol/rx", [])}
    for k, t in tel.items():
        if bool(t.dropped) == (k in fwd):
            return _verdict(name, FAIL, f"sample {k}: telemetry dropped = {t.dropped}, but the symbol was "
                                        f"{'forwarded' if k in fwd else 'not forwarded'}")
    return _verdict(name, PASS, "every symbol forwarded or dropped as the telemetry says")


def _acks(role, rec, s, N, T, d, stall_again) -> dict:
    name = "acks_and_deadlines"
    problems = []
    act: dict = {}
    for m in rec.loop.get("/loop/actuation", []):
        act.setdefault(m.k, m)  # the first copy counts (a later one: late, or an adverse case's)
    last = -1
    for k in range(N):
        m = act.get(k)
        if m is None:
            continue
        if m.theta == 0:
            last = k
        if m.last_rx != last:
            problems.append(f"sample {k}: actuation last_rx {m.last_rx}, the latest accepted sample is {last}")
            break
        if role == "controller" and m.stamp_ns > k * T + d * T:
            problems.append(f"sample {k}: u_k published at {m.stamp_ns} ns, after the plant's deadline "
                            f"{int(k * T + d * T)} ns")
            break
    tm = s.get("timing") or {}
    if tm.get("deadline_misses"):
        problems.append(f"{tm['deadline_misses']} deadline misses at samples {s.get('deadline_missed_at')}")
    ev = s.get("events") or {}
    if ev.get("ack_missing") and not s.get("ack_via_attacker"):
        problems.append(f"{ev['ack_missing']} acks missed the encoder's grace window")
    if not problems:
        return _verdict(name, PASS, "every actuation's ack (theta_k, last_rx) as Algorithm 2 says; no deadline missed")
    return _verdict(name, INCONCLUSIVE if stall_again else FAIL,
                    problems[0] + (f" (the run stalled twice: {stall_again})" if stall_again else ""))


def _stop(role, rec, r: ExternalRun, s) -> dict:
    name = "clean_stop"
    if role == "plant" and not any(st.origin == "plant" for st in rec.stops):
        return _verdict(name, FAIL, "the plant published no Stop (origin plant) at the end of the run")
    if r.command_stopped_s is None:
        return _verdict(name, FAIL, f"the command was still running {STOP_GRACE_S:g} s after the run ended "
                                    "(stopped with SIGINT/SIGKILL)")
    if r.command_rc != 0:
        return _verdict(name, FAIL, f"the command exited with status {r.command_rc}: {_last(r.command_log)!r}")
    if role not in rec.summaries:
        return _verdict(name, FAIL, f"no NodeSummary on summary/{role}")
    tm = [f for f in s.get("faults", []) if f.get("node") == role and f.get("kind") == "telemetry_mismatch"
          and not (role == "attacker" and r.fed)]  # it records every symbol it got, the adverse copies too
    if tm:
        return _verdict(name, FAIL, f"its summary's telemetry count or digest differs from what arrived: {tm[0].get('why')}")
    if not r.join_removed:
        return _verdict(name, FAIL, f"the join file {r.join_path} was left behind")
    return _verdict(name, PASS, f"the command exited 0, {r.command_stopped_s:g} s after the run ended, with its "
                                "summary; the join file was removed")


def conformance(role: str, scenario: str, command: list[str], *, folder: Path, run_id: str,
                flags: Sequence[str] = (),
                timeout: float = 300.0, startup_timeout: float = 120.0, feed: bool = True,
                session: SessionOptions | None = None, bit_exact: bool = False, plant_tolerance: float = PLANT_TOLERANCE,
                replay: Callable[[str], dict] | None = None) -> dict:
    """Run and check (once more if the run stalled): ``{"passed", "requirements", "runs"}``; ``passed`` is over
    the required requirements (``check_run``: ``bit_exact``, ``plant_tolerance``, ``replay``)."""
    runs = []
    stall_again = None
    for attempt in range(2):
        r = run_external(role, scenario, command, run_id=run_id + "r" * attempt, folder=folder, flags=flags,
                         timeout=timeout, startup_timeout=startup_timeout, feed=feed, session=session)
        runs.append(r)
        st = stalled(r.summary, role) if r.summary else None
        if not st:
            break
        if attempt:
            stall_again = st
    reqs = check_run(role, scenario, runs[-1], stall_again=stall_again, bit_exact=bit_exact,
                     plant_tolerance=plant_tolerance, replay=replay)
    return {"passed": all(q["passed"] for q in reqs if q["required"]), "role": role, "scenario": scenario,
            "command": command, "bit_exact": bit_exact,
            "requirements": reqs,
            "runs": [{"run_id": run_id + "r" * i, "rc": r.rc, "outcome": (r.summary or {}).get("outcome"),
                      "stalled": stalled(r.summary, role) if r.summary else None, "command_rc": r.command_rc,
                      "report": own_report(r.summary, role),
                      "recording": r.recording, "fed": r.fed, "notes": r.notes} for i, r in enumerate(runs)]}
