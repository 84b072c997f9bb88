"""``testbed report RUN.mcap [--json] [--plot PATH.png]``: the post-mortem of a recording.

Everything comes from the recording alone: the scenario is rebuilt from the
TOML stored in its metadata (with the run's overrides), the per-sample arrays
from the telemetry topics.  They go through the same
``testbed.runsummary.build_summary`` as ``testbed run`` (and, inside it,
``testbed.simulate.summarize``), so every key of ``testbed simulate --json`` means
the same thing here.  Added beside them:

* ``dos``: the attack intervals as the attacker logged them (its per-sample
  ``attack_on``), their lengths, the realized rates N(H)/H and |A(H)|/H, and the
  smallest kappa_F, kappa_D at the scenario's rho_F, rho_D (``attackers.budget.check``),
  checked against the scenario's declared budget when it has one;
* ``agreement``: encoder and decoder xi_k, E_k compared at every sample;
* ``saturation_events``, ``dropped_by_attacker``, ``recording`` (source,
  truncation, message counts, software versions);
* ``plant_source``: how the plant module was loaded, ``{"ref", "sha256",
  "loaded_from": "import" | "recording", "differs", ...}`` (None for recordings
  that store no plant module), and ``model_source`` the same for a ``[model]`` of
  another class.  The stored source is used only when the module cannot be
  imported, and then the report says so.

Exit codes: 0 report written, 2 unreadable file or no scenario in it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from .io import messages as msg
from .io import recording as rec_io
from .runsummary import ROLES, RunData, build_summary


def _budget_section(sc, attack_on: np.ndarray, horizon: float) -> dict:
    from attackers.budget import check, realized_rates
    from attackers.schedule import Schedule

    sch = Schedule.from_theta(attack_on.astype(np.uint8), sc.T) if attack_on.size else Schedule.empty()
    out: dict = {"intervals": [list(iv) for iv in sch.intervals], "count": len(sch),
                 "lengths": [float(x) for x in sch.lengths], "total_duration": float(sch.total_duration),
                 "horizon": horizon}
    if horizon > 0:
        rr = realized_rates(sch, horizon)
        out["realized"] = {"frequency": rr[0], "duration_fraction": rr[1]}
    declared = sc.attack.budget
    if declared is not None:
        kF, rF, kD, rD = declared
        rep = check(sch, rF, rD, horizon=horizon if horizon > 0 else None)
        out["budget"] = {"declared": {"kappa_F": kF, "rho_F": rF, "kappa_D": kD, "rho_D": rD},
                         "kappa_F_min": rep.kappa_F_min, "kappa_D_min": rep.kappa_D_min,
                         "within": bool(rep.satisfies(kF, kD))}
    else:
        out["budget"] = None
    return out


def _actuation_section(sc, data: RunData, N: int) -> dict | None:
    """Physical timing: the delays the plant measured and the bounds and margins the quantizer used."""
    if sc.run.timing != "physical":
        return None
    from .runsummary import percentiles

    P = data.tele.get("plant", {})
    tp = sc.timing_params
    qp = sc.quantizer
    recv, lost, arrival, late = [], [], [], 0
    for k in range(N):
        p = P.get(k)
        if p is None:
            continue
        (lost if p.theta == 1 else recv).append(p.delay_ns)
        if p.u_rx_ns != msg.NO_TIME and p.t_ns != msg.NO_TIME and p.theta == 0:
            arrival.append(p.u_rx_ns - p.t_ns)
            if sc.run.actuation == "scheduled" and p.theta == 0 and p.u_rx_ns - p.t_ns > int(tp[2]):
                late += 1

    def bound(d):
        return None if d is None else {"nominal": d.nominal, "min": d.min, "max": d.max, "declared": d.declared}

    return {"actuation": sc.run.actuation, "rule": qp.rule, "scheduled_delay_s": int(tp[2]) / 1e9,
            "deadline_s": int(tp[3]) / 1e9, "loss_deadline_s": int(tp[4]) / 1e9,
            "bound": bound(sc.run.delay), "bound_lost": bound(sc.run.delay_lost),
            "delay_hat": qp.delay_hat, "margin_gain": qp.margin_gain, "delay_hat_lost": qp.delay_hat_lost,
            "margin_gain_lost": qp.margin_gain_lost, "L_u": sc.L_u,
            "delay_us": {"received": percentiles(recv), "lost": percentiles(lost)},
            "arrival_us": percentiles(arrival), "late_for_schedule": late}


def _agreement(data: RunData, N: int) -> dict:
    enc, ctl = data.tele.get("encoder", {}), data.tele.get("controller", {})
    compared, differ, missing = 0, [], []
    for k in range(N):
        e, c = enc.get(k), ctl.get(k)
        if e is None or c is None or e.silent:
            missing.append(k)
            continue
        compared += 1
        if e.E != c.E or tuple(e.xi) != tuple(c.xi):
            differ.append(k)
    return {"samples": N, "compared": compared, "disagree": len(differ), "disagree_at": differ[:50],
            "not_compared": len(missing), "not_compared_at": missing[:50], "all_agree": not differ and not missing}


def report(path: str | Path | rec_io.Recording) -> dict:
    """The report of one recording (a path, or a ``Recording`` already read), as a JSON-able dict."""
    with rec_io.no_gc():
        return _report(path)


def _report(path: str | Path | rec_io.Recording) -> dict:
    from .quantizer import Codebook

    rec = path if isinstance(path, rec_io.Recording) else rec_io.read(path)
    path = rec.path
    sc = rec.scenario()
    runmeta = rec.metadata.get("testbed.run", {})
    data = RunData(tele={r: rec.telemetry.get(r, {}) for r in ROLES}, plant_final=rec.plant_final,
                   events=rec.events, status=rec.status, summaries=rec.summaries)
    launcher = rec.summaries.get("launcher", {})
    plant = sc.make_model()
    cb = Codebook(plant.n, sc.quantizer.M, resilient=(sc.quantizer.mode == "resilient"))
    run_id = rec.start.run_id if rec.start else runmeta.get("run_id", "?")
    ack_via = runmeta.get("ack_via_attacker", "false") == "true" or bool(rec.start and rec.start.ack_via_attacker)
    out = build_summary(sc, data, run_id=run_id, ack_via_attacker=ack_via, nodes=launcher.get("nodes") or {},
                        faults=launcher.get("faults") or [], codebook=cb)
    live = rec.source == "live"
    out["live"] = live
    out["source"] = rec.source
    N = out["samples"]
    if not live:
        out["timing"] = None  # a simulation has nominal times only
    A = data.tele.get("attacker", {})
    attack_on = np.array([bool(A[k].attack_on) if k in A else False for k in range(N)])
    dropped = np.array([bool(A[k].dropped) if k in A else False for k in range(N)])
    out["dos"] = _budget_section(sc, attack_on, N * sc.T)
    out["dos"]["attacker_log_samples"] = len(A)
    out["dropped_by_attacker"] = int(dropped.sum())
    out["agreement"] = _agreement(data, N)
    out["saturation_events"] = [e.k for e in rec.events if e.kind == "saturation"]
    out["outcome"] = launcher.get("outcome", "simulated" if not live else None)
    out["actuation"] = _actuation_section(sc, data, N)
    from .resimulate import compare, recorded_run

    try:
        out["resimulation"] = compare(recorded_run(rec))
    except Exception as e:  # noqa: BLE001 - the report stands without it; say why
        out["resimulation"] = {"reproduced": None, "verdict": f"not resimulated: {type(e).__name__}: {e}"}
    last_t = (rec.last_log_time - rec.start.t0_ns) / 1e9 if rec.start and rec.last_log_time else None
    out["recording"] = {
        "path": str(path), "source": rec.source, "truncated": rec.truncated, "read_error": rec.read_error,
        "complete": not rec.truncated and "testbed.recorder" in rec.metadata,
        "messages": dict(rec.counts), "last_message_s": last_t, "duplicates": rec.duplicates,
        "malformed": len(rec.malformed), "software": rec.metadata.get("testbed.software", {}),
        "recorder": rec.metadata.get("testbed.recorder"), "scenario_ref": rec.metadata.get("testbed.scenario", {}).get("ref"),
        "overrides": json.loads(runmeta.get("scenario_overrides", "{}") or "{}"),
    }
    out["plant_source"] = rec.plant_source
    out["model_source"] = rec.model_source
    return out


def plot(summary: dict, path: str | Path, *, title: str = "") -> Path:
    """The paper's Fig. 2 from a report: states, input, E_k at encoder and decoder, DoS shaded."""
    from types import SimpleNamespace

    from .analysis.figures import plot_time_series

    def arr(key):
        v = summary.get(key) or []
        return np.array([[np.nan if a is None else a for a in row] if isinstance(row, list) else
                         (np.nan if row is None else row) for row in v], dtype=float)

    res = SimpleNamespace(T=summary["T"], t=np.asarray(summary["t"], dtype=float), x=arr("x"), u=arr("u"),
                          E_enc=arr("E"), E_dec=arr("E_dec"), theta=np.asarray(summary["theta"], dtype=int))
    intervals = summary.get("dos", {}).get("intervals")
    return plot_time_series(res, path, title=title or f"{summary.get('scenario')} ({summary.get('source')})",
                            intervals=intervals)


def print_text(s: dict) -> None:
    r = s["recording"]
    verdict = "converged" if s.get("converged") else ("ESCAPED" if s.get("escaped") else "not converged")
    print(f"{r['path']}: {s['source']} run {s['run_id']}, scenario {s['scenario']} (plant {s['plant']}), "
          f"{s['samples']}/{s['n_steps']} samples of T = {s['T']:g} s"
          + (" [TRUNCATED: read up to the last complete chunk]" if r["truncated"] else ""))
    if (s.get("plant"), s.get("plant_params")) != (s.get("model"), s.get("model_params")):
        print(f"  true plant {s['plant']} {s.get('plant_params')}, model {s.get('model')} {s.get('model_params')} "
              "(predictions, design)")
    for what in ("plant", "model"):
        ps = s.get(f"{what}_source")
        if ps and ps["loaded_from"] == "recording":
            print(f"  {what} {ps['ref']}: module {ps.get('module')!r} not importable; used the source stored in the "
                  f"recording (sha256 {ps['sha256'][:12]})")
        elif ps and ps["differs"]:
            print(f"  {what} {ps['ref']}: the importable module {ps.get('module')!r} DIFFERS from the recorded one "
                  f"(sha256 {(ps['importable_sha256'] or '')[:12]} now, {ps['sha256'][:12]} recorded)")
    fn = s.get("final_norm")
    if s["samples"] == 0:
        print("  NO SAMPLES recorded (the run never started, or the recorder died before it did)")
    else:
        print(f"  final ||x||_inf = {fn:.3e} -> {verdict}" if fn is not None else "  no final state")
    if s.get("plant_fault"):
        print(f"  PLANT FAULT at sample {s['plant_fault_at']}: {s['plant_fault']} (the run ended there)")
    d = s["dos"]
    lens = ", ".join(f"{x:g}" for x in d["lengths"][:8]) + (" ..." if len(d["lengths"]) > 8 else "")
    print(f"  DoS: {d['count']} intervals (lengths {lens or '-'} s), {s['packets_dropped']} samples lost "
          f"({s['dropped_by_attacker']} dropped by the attacker)")
    if d.get("realized"):
        print(f"  realized rates: N(H)/H = {d['realized']['frequency']:.4g} /s, "
              f"|A(H)|/H = {d['realized']['duration_fraction']:.4g}")
    b = d.get("budget")
    if b:
        dec = b["declared"]
        print(f"  budget (kappa_F {dec['kappa_F']:g}, rho_F {dec['rho_F']:g}, kappa_D {dec['kappa_D']:g}, "
              f"rho_D {dec['rho_D']:g}): needs kappa_F >= {b['kappa_F_min']:.4g}, kappa_D >= {b['kappa_D_min']:.4g}"
              f" -> {'within' if b['within'] else 'EXCEEDED'}")
    else:
        print("  budget: the scenario declares none")
    ag = s["agreement"]
    print(f"  encoder/decoder agreement: {ag['compared'] - ag['disagree']}/{ag['compared']} samples identical"
          + (f", {ag['not_compared']} not comparable (withheld or missing)" if ag["not_compared"] else "")
          + (f"; DISAGREE at {ag['disagree_at'][:10]}" if ag["disagree"] else ""))
    print(f"  saturations: {s.get('saturations', 0)}" + (f" at {s['saturated_at'][:10]}" if s.get("saturated_at") else ""))
    tm = s.get("timing")
    if tm:
        from .launcher import _fmt

        print(f"  sampling jitter      {_fmt(tm['sampling_jitter_us'])}")
        print(f"  sensor-to-actuator   {_fmt(tm['sensor_to_actuator_us'])}")
        print(f"  deadline misses {tm['deadline_misses']}, overruns {tm['overruns']}")
    act = s.get("actuation")
    if act:
        from .launcher import _fmt

        print(f"  physical timing, {act['actuation']} actuation"
              + (f" at t_k + {act['scheduled_delay_s'] * 1e3:g} ms" if act["actuation"] == "scheduled" else "")
              + f", {act['rule']} rule (nominal delay {act['delay_hat'] * 1e3:g} ms, margin "
                f"{act['margin_gain']:.3g} ||u_k - u_k-1||; lost samples {act['delay_hat_lost'] * 1e3:g} ms, "
                f"margin {act['margin_gain_lost']:.3g})")
        print(f"  u_k of a received sample arrived after t_k: {_fmt(act['arrival_us'])}"
              + (f"; {act['late_for_schedule']} later than scheduled" if act["actuation"] == "scheduled" else ""))
    rs = s.get("resimulation")
    if rs:
        print(f"  resimulation: {rs['verdict']}"
              + (f" (max state error {rs['max_state_error']:.3g})" if rs.get("max_state_error") else ""))
    for f in s.get("faults") or []:
        print(f"  FAULT {f.get('node')}: {f.get('kind')} ({f.get('why')})")
    if s.get("events"):
        print("  events: " + ", ".join(f"{k} x{v}" for k, v in sorted(s["events"].items())))


def add_arguments_report(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", help="an MCAP file written by testbed run or testbed simulate --out")
    p.add_argument("--json", action="store_true", help="print one JSON object (keys as testbed simulate --json)")
    p.add_argument("--plot", metavar="PATH.png", help="draw states, input, E_k and the DoS intervals")


def main_report(args) -> int:
    try:
        s = report(args.recording)
    except (OSError, ValueError) as e:
        print(f"testbed report: {args.recording}: {e}", file=sys.stderr)
        return 2
    if args.plot:
        plot(s, args.plot)
    if args.json:
        sys.stdout.write(json.dumps(s))  # the C encoder in one go: 2x json.dump on long runs
        sys.stdout.write("\n")
    else:
        print_text(s)
        if args.plot:
            print(f"  figure: {args.plot}")
    return 0


