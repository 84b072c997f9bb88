"""``testbed run SCENARIO``: a live run's flags, and its summary as text or JSON."""

from __future__ import annotations

import argparse
import shutil
import sys

from ..common import cliargs, optionspec
from ..live.external import add_external_arguments
from ..live.launcher import Launcher
from ..live.netns import add_cut_arguments, add_netns_arguments, main_clean
from ..live.recorder import add_record_error_argument
from ..loop.channel import loss_text
from ..nodes.options import RunConfig, add_run_option_arguments
from ..record.faulttext import fault_line
from ..record.timingstats import fmt_percentiles
from ..scenario import rulesofthumb
from ..view.rerun import add_rerun_run_arguments
from ..wire.session import add_network_arguments
from .liveconfig import run_config


def add_arguments_run(p: argparse.ArgumentParser) -> None:
    """``testbed run``'s flags: the options of ``RunConfig`` by their groups (``testbed.common.optionspec``), and those the
    modules that use them define."""
    p.add_argument("scenario", nargs="?", help="scenario file (.toml) or bundled name")
    cliargs.add_json(p, "the run's summary (the keys of testbed simulate --json, plus timing and faults)")
    add_run_option_arguments(p)
    g = p.add_argument_group("network")
    add_network_arguments(g, launcher=True)
    optionspec.add_arguments(p, RunConfig, "run", group=g, section="network")
    add_netns_arguments(g)
    g = p.add_argument_group("recording")
    cliargs.add_out(g, "recording file (default recordings/<scenario>-<UTC start>-<run id>.mcap); "
                       "never overwritten", aliases=("--record",))
    optionspec.add_arguments(p, RunConfig, "run", group=g, names=("force", "no_record"))
    add_record_error_argument(g)
    optionspec.add_arguments(p, RunConfig, "run", group=g, names=("record_loop",))
    add_rerun_run_arguments(p)
    optionspec.add_arguments(p, RunConfig, "run", section="foxglove (live view)")
    add_external_arguments(p)
    optionspec.add_arguments(p, RunConfig, "run", section="run control")
    g = p.add_argument_group("fault injection")
    optionspec.add_arguments(p, RunConfig, "run", group=g, section="fault injection")
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


def main_run(args: argparse.Namespace) -> int:
    from ..common.errors import BadInput

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
