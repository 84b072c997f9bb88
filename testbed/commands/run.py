"""``testbed run SCENARIO``: a live run's flags, and its summary as text or JSON."""

from __future__ import annotations

import argparse
import shutil
import sys

from .. import cliargs, rulesofthumb
from ..channel import loss_text
from ..live.external import add_external_arguments
from ..live.launcher import Launcher
from ..live.netns import add_cut_arguments, add_netns_arguments, main_clean
from ..live.recorder import add_record_error_argument
from ..nodes.inlet import RX_MODES
from ..nodes.options import add_run_option_arguments
from ..record.faulttext import fault_line
from ..stats import fmt_percentiles
from ..view.rerun import add_rerun_run_arguments
from ..wire.session import add_network_arguments
from .liveconfig import run_config

#: ``--foxglove``'s port when none is given
FOXGLOVE_PORT = 8765


def add_foxglove_run_arguments(p) -> None:
    """The ``--foxglove`` option of ``testbed run``."""
    g = p.add_argument_group("foxglove (live view)")
    g.add_argument("--foxglove", nargs="?", type=int, const=FOXGLOVE_PORT, default=None, metavar="PORT",
                   help=f"serve the run live over Foxglove's WebSocket protocol on 127.0.0.1:PORT (default "
                        f"{FOXGLOVE_PORT}; needs foxglove-sdk); connect Foxglove to ws://127.0.0.1:PORT")
    g.add_argument("--foxglove-linger", type=float, default=0.0, metavar="S",
                   help="keep the server up S seconds after the run (default %(default)s)")


def add_arguments_run(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", nargs="?", help="scenario file (.toml) or bundled name")
    cliargs.add_json(p, "the run's summary (the keys of testbed simulate --json, plus timing and faults)")
    add_run_option_arguments(p)
    g = p.add_argument_group("network")
    add_network_arguments(g, launcher=True)
    g.add_argument("--node-connect", metavar="ENDPOINT",
                   help="endpoint the nodes connect to (default: --listen)")
    g.add_argument("--node-listen", action="append", default=[], metavar="ROLE=ENDPOINT",
                   help="a node's own listener (default tcp/127.0.0.1:0), e.g. plant=tcp/10.0.0.2:0")
    g.add_argument("--node-prefix", action="append", default=[], metavar="ROLE=COMMAND",
                   help="run a node under a command, e.g. plant='ip netns exec tb-plant' or 'ssh host'")
    add_netns_arguments(g)
    g = p.add_argument_group("recording")
    cliargs.add_out(g, "recording file (default recordings/<scenario>-<UTC start>-<run id>.mcap); "
                       "never overwritten", aliases=("--record",))
    g.add_argument("--force", action="store_true", help="replace an existing --out file")
    g.add_argument("--no-record", action="store_true", help="do not record the run")
    add_record_error_argument(g)
    g.add_argument("--record-loop", choices=["auto", "on", "off"], default="auto",
                   help="also record the control-path messages (auto: when T >= 10 ms)")
    add_rerun_run_arguments(p)
    add_foxglove_run_arguments(p)
    add_external_arguments(p)
    g = p.add_argument_group("run control")
    g.add_argument("--startup-timeout", type=float, default=120.0, metavar="S",
                   help="give up if the nodes are not running after S seconds (default %(default)s)")
    g.add_argument("--run-dir", help="directory for node logs (default: a temporary one, kept on faults)")
    g.add_argument("--spawn", choices=["fork", "exec"], default="fork",
                   help="how local nodes start: fork (default) from the launcher, which has loaded Python, numba "
                        "and the loop's compiled kernels once, or exec (a fresh 'python -m testbed.cli node' per "
                        "node, as with --node-prefix, which always execs)")
    g.add_argument("--realtime", action="store_true", help="nodes try SCHED_FIFO")
    g.add_argument("--cpu", action="append", default=[], metavar="WHO=CPUS",
                   help="pin a node (plant, encoder, attacker, controller), the recorder or the launcher (the "
                        "run's router) to CPUs, e.g. plant=2 or launcher=0,1 (repeatable)")
    g.add_argument("--rx", choices=RX_MODES, help="how the nodes receive control messages (testbed node --rx)")
    g.add_argument("--rx-spin-us", type=float, help="--rx spin: spin budget per sample (us)")
    g.add_argument("--spin-us", type=float, help="plant busy-wait before each sample instant (us)")
    g.add_argument("--ack-grace", type=float, help="encoder grace for a late ack, fraction of T")
    g.add_argument("-v", "--verbose", action="store_true", help="nodes log at INFO")
    g.add_argument("--progress", action="store_true",
                   help="the status line (sample k of N, losses by cause, deadline misses, E_k at both ends, about "
                        "once a second) on stderr even when it is not a terminal (on a terminal it is always shown)")
    g = p.add_argument_group("fault injection")
    g.add_argument("--kill", action="append", default=[], metavar="ROLE@SECONDS",
                   help="SIGKILL a node (or the recorder) SECONDS after t0 (repeatable)")
    g.add_argument("--stall", action="append", default=[], metavar="ROLE@SECONDS:DURATION",
                   help="freeze a node's process (SIGSTOP) SECONDS after t0 and resume it (SIGCONT) DURATION "
                        "seconds later (repeatable)")
    g.add_argument("--crash", action="append", default=[], metavar="ROLE@K",
                   help="make a node raise at sample K (repeatable)")
    g.add_argument("--corrupt", metavar="K[:range|:length],...",
                   help="the attacker corrupts the payload of these samples")
    add_cut_arguments(g)


def print_text(s: dict) -> None:
    if not s.get("samples"):  # nothing ran: no loop figures to show, only why
        print(f"run {s['run_id']}: scenario {s.get('scenario')}: the run NEVER STARTED (outcome: {s['outcome']})")
        for f in s["faults"]:
            print(f"  {fault_line(f)}")
        if s.get("run_dir"):
            print(f"  node logs: {s['run_dir']}")
        return
    tm = s["timing"]
    from ..sim.batch import outcome_text  # loaded with the summary already

    verdict = outcome_text(s)
    print(f"run {s['run_id']}: scenario {s.get('scenario')}, {s['samples']}/{s['n_steps']} samples, "
          f"T = {tm['T_us'] / 1e6:g} s, timing {s['timing_mode']}, outcome: {s['outcome']}")
    sec = s.get("security") or {}
    if sec:
        print(f"  {sec['topology']} topology" + (f" (auto: {sec['topology_why']})" if sec.get("topology_auto") else "")
              + f", {sec['transport']}")
    # every lost sample under its one cause (``losses``, ``channel.recorded_losses``): the causes add up
    print(f"  {s.get('packets_dropped', 0)} samples lost ({loss_text(s['losses'])}; invalid payloads "
          f"{s.get('invalid_payloads')}), {s.get('saturations', 0)} saturations, encoder/decoder agree: "
          f"{s.get('encoder_decoder_agree_where_known')}" + ("" if s.get("encoder_decoder_agree") else
                                                              " (on the samples both recorded)"))
    fn = s.get("final_norm")
    print(f"  final ||x||_inf = {fn:.3e} -> {verdict}" if fn is not None else "  no final state")
    print(f"  sampling jitter      {fmt_percentiles(tm['sampling_jitter_us'])}")
    print(f"  sensor-to-actuator   {fmt_percentiles(tm['sensor_to_actuator_us'])}")
    for st, v in tm["stages_us"].items():
        print(f"    {st:18s} {fmt_percentiles(v)}")
    print(f"  deadline misses {tm['deadline_misses']}, overruns {tm['overruns']}; symbol payload "
          f"{s['sizes']['symbol_payload_bytes']} B + header {s['sizes']['header_bytes']} B")
    if s.get("timing_degraded"):
        print(f"  TIMING DEGRADED: {s['timing_degraded_why']}")
    if s["controller_lost_at"] is not None and s["controller_lost_at"] >= 0:
        print(f"  controller lost at sample {s['controller_lost_at']}: plant ran on with u = 0")
    for f in s["faults"]:
        print(f"  {fault_line(f)}")
    rec = s.get("recording")
    if rec:
        print(f"  recording: {rec['path']}" + ("" if rec["complete"] else " (INCOMPLETE: the recorder did not "
                                                                          "finish; readable up to its last flush)")
              + (f": {rec['error']}" if rec.get("error") else ""))
    if s.get("run_dir"):
        print(f"  node logs: {s['run_dir']}")


def main_run(args) -> int:
    from ..errors import BadInput

    if args.netns_clean:  # only that
        return main_clean()
    if args.scenario is None:
        raise BadInput("which scenario? (a .toml file or a bundled name; testbed scenarios lists them)")
    cfg = run_config(args)  # the run's typed configuration, built once: the launcher and the nodes get it
    launcher = Launcher(cfg)
    for line in rulesofthumb.warnings(launcher.sc):  # a documented rule of thumb broken: said before the run
        print(f"testbed run: warning: {line}", file=sys.stderr)
    try:
        code, summary = launcher.run()
    except BadInput:  # refused before any node ran (certificates, ...): no run folder left behind
        if launcher.own_dir and not any(launcher.run_dir.glob("*.log")):
            shutil.rmtree(launcher.run_dir, ignore_errors=True)
        raise
    launcher.phase("closed")
    if cfg.json:
        from ..record.summary import write_json

        write_json(summary, sys.stdout)  # streamed: no list of every sample in memory
        sys.stdout.write("\n")
    else:
        print_text(summary)
    sys.stdout.flush()
    launcher.phase("printed")
    return code
