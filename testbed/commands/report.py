"""``testbed report RUN.mcap [--json] [--plot PATH]``: the post-mortem of a recording.

Its arguments and text output; the report itself is ``testbed.runs.report``.
"""

from __future__ import annotations

import argparse
import sys

from ..common import cliargs
from ..record.faulttext import fault_line
from ..record.summary import write_json
from ..record.timingstats import fmt_percentiles
from ..runs import report as reports
from ..runs.report import plot, report_of_run, run_of


def print_text(s: dict) -> None:
    r = s["recording"]
    from ..sim.batch import outcome_text  # loaded with the summary already

    verdict = outcome_text(s)
    print(f"{r['path']}: {s['source']} run {s['run_id']}, scenario {s['scenario']} (plant {s['plant']}), "
          f"{s['samples']}/{s['n_steps']} samples of T = {s['T']:g} s"
          + (" [TRUNCATED: read up to the last complete chunk]" if r["truncated"] else ""))
    if r.get("ends"):
        print(f"  INCOMPLETE RECORDING: {r['ends']}")
    if (s.get("plant"), s.get("plant_params")) != (s.get("model"), s.get("model_params")):
        print(f"  true plant {s['plant']} {s.get('plant_params')}, model {s.get('model')} {s.get('model_params')} "
              "(predictions, design)")
    for what in ("plant", "model"):
        ps = s.get(f"{what}_source")
        if ps and ps["loaded_from"] == "recording":
            print(f"  {what} {ps['ref']}: module {ps.get('module')!r} not importable; used the source stored in the "
                  f"recording (sha256 {ps['sha256'][:12]}, --trust-code)")
        elif ps and ps["loaded_from"] == "not run":
            print(f"  {what} {ps['ref']}: module {ps.get('module')!r} not importable; the source stored in the "
                  "recording was not run (--trust-code runs it)")
        elif ps and ps["differs"]:
            print(f"  {what} {ps['ref']}: the importable module {ps.get('module')!r} DIFFERS from the recorded one "
                  f"(sha256 {(ps['importable_sha256'] or '')[:12]} now, {ps['sha256'][:12]} recorded)")
    sec = r.get("security")
    if sec and not sec.get("authenticated"):
        print("  INSECURE run: no authentication, no access control (any local process could have joined it)")
    bad = sum(r["rejected"].values()) if r.get("rejected") else 0
    if bad or r.get("malformed"):
        print(f"  WARNING: {bad} telemetry messages rejected (k outside [0, N)), {r.get('malformed', 0)} malformed:"
              " the results below leave them out")
    fn = s.get("final_norm")
    if s["samples"] == 0:
        print("  NO SAMPLES recorded (the run never started, or the recorder died before it did)")
    else:
        print(f"  final ||x||_inf = {fn:.3e} -> {verdict}" if fn is not None else "  no final state")
    if s.get("plant_fault"):
        print(f"  PLANT FAULT at sample {s['plant_fault_at']}: {s['plant_fault']} (the run ended there)")
    if s.get("method_fault"):
        print(f"  METHOD FAULT at sample {s['method_fault_at']}: {s['method_fault']} (the run ended there)")
    if s.get("lockstep_breaks"):
        print(f"  LOCKSTEP BROKEN: the method's encoder and decoder disagree from sample {s['lockstep_breaks'][0]} "
              f"({len(s['lockstep_breaks'])} samples)")
    for f in s.get("telemetry_check") or []:
        print(f"  TELEMETRY MISMATCH {f['node']}: {f['why']}")
    d = s["dos"]
    lens = ", ".join(f"{x:g}" for x in d["lengths"][:8]) + (" ..." if len(d["lengths"]) > 8 else "")
    print(f"  DoS: {d['count']} intervals (lengths {lens or '-'} s), {s['packets_dropped']} samples lost "
          f"({s['dropped_by_attacker']} dropped by the attacker)")
    if d.get("realized"):
        print(f"  realized rates: N(H)/H = {d['realized']['frequency']:.4g} /s, "
              f"|A(H)|/H = {d['realized']['duration_fraction']:.4g}")
    ls = s.get("losses")
    if ls:
        from ..loop.channel import loss_text

        print(f"  losses by cause: {loss_text(ls)} (the budget below counts the attacker's only)")
    ld = s.get("losses_as_dos") or {}
    if "frequency" in ld:
        th1 = ld.get("theorem1") or {}
        ok = th1.get("in_allowable_region")
        print(f"  all losses as DoS over H = {ld['horizon']:g} s: N(H)/H = {ld['frequency']:.4g} /s, "
              f"|A(H)|/H = {ld['duration_fraction']:.4g}, taken as rates rho_F, rho_D with no intercepts -> "
              + ("inside" if ok else "OUTSIDE" if ok is not None else "unknown (" + th1.get("why", "") + "):")
              + " Theorem 1's allowable region (paper's rule)")
        bd = th1.get("budget")
        if bd:
            print(f"  the scenario's budget as testbed analyze checks it (rho_F {bd['rho_F']:.4g}, rho_D "
                  f"{bd['rho_D']:.4g}, intercepts kappa_F {bd['kappa_F']:.4g}, kappa_D {bd['kappa_D']:.4g}; "
                  f"{bd['source']}) -> {'inside' if bd['in_allowable_region'] else 'OUTSIDE'} Theorem 1's "
                  "allowable region: Theorem 1 bounds the long-run rates; a finite run's excess is in the intercepts")
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
    sat_at = list(s.get("saturated_at", [])[:10])
    print(f"  saturations: {s.get('saturations', 0)}" + (f" at {[int(k) for k in sat_at]}" if sat_at else ""))
    act = s.get("actuation")
    if act:
        print(f"  physical timing, {act['actuation']} actuation"
              + (f" at t_k + {act['scheduled_delay_s'] * 1e3:g} ms" if act["actuation"] == "scheduled" else "")
              + f", {act['rule']} rule (nominal delay {act['delay_hat'] * 1e3:g} ms, margin "
                f"{act['margin_gain']:.3g} ||u_k - u_k-1||; lost samples {act['delay_hat_lost'] * 1e3:g} ms, "
                f"margin {act['margin_gain_lost']:.3g})")
        print(f"  u_k of a received sample arrived after t_k: {fmt_percentiles(act['arrival_us'])}"
              + (f"; {act['late_for_schedule']} later than scheduled" if act["actuation"] == "scheduled" else ""))
    rs = s.get("resimulation")
    if rs:
        print(f"  resimulation{' ' + rs['plant_line'] if rs.get('plant_line') else ''}: {rs['verdict']}"
              + (f" (max state error {rs['max_state_error']:.3g})" if rs.get("max_state_error") else ""))
    tm = s.get("timing")
    if tm:
        print(f"  sampling jitter      {fmt_percentiles(tm['sampling_jitter_us'])}")
        print(f"  sensor-to-actuator   {fmt_percentiles(tm['sensor_to_actuator_us'])}")
        print(f"  deadline misses {tm['deadline_misses']}, overruns {tm['overruns']}")
    if s.get("timing_degraded"):
        print(f"  TIMING DEGRADED: {s['timing_degraded_why']}")
    for f in s.get("faults") or []:
        print(f"  {fault_line(f)}")
    if s.get("events"):
        print("  events: " + ", ".join(f"{k} x{v}" for k, v in sorted(s["events"].items())))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", help="an MCAP file written by testbed run or testbed simulate --out")
    cliargs.add_json(p, "the report (the keys of testbed simulate --json and more)")
    cliargs.add_plot(p, "draw states, input, E_k and the DoS intervals (the figure of testbed simulate --plot)")
    n = reports.RESIMULATE_SAMPLES  # read when the parser is made (a test may change it)
    p.add_argument("--resimulate", metavar="N|all", type=cliargs.int_at_least(0, or_all=True), default=n,
                   help=f"re-run the first N samples in the simulator and compare (default {n:,}; "
                        "all: every sample, as testbed resimulate; 0: none)")
    cliargs.add_trust_code(p)


def main(args: argparse.Namespace) -> int:
    run = run_of(args.recording, trust_code=args.trust_code)
    s = report_of_run(run, resimulate=args.resimulate)
    if args.plot:
        plot(run, args.plot, size=args.figsize)
    if args.json:
        write_json(s, sys.stdout)  # streamed: no list of every sample in memory
        sys.stdout.write("\n")
    else:
        print_text(s)
        if args.plot:
            print(f"  figure: {args.plot}")
    return 0
