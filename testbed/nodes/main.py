"""``testbed node plant|encoder|attacker|controller SCENARIO [zenoh options]``: one node of a live run.

Life of a node: open the Zenoh session, declare, warm up (JIT), collect and
freeze the garbage, declare the ``alive/<role>`` token, wait until the four
roles are alive, warm up the publishers, declare ``ready/<role>``; the plant
then waits for every ``ready`` token and publishes ``Start`` (t0), the others
wait for it; run; publish a summary; close the session.  With ``-v`` each step
is a ``phase`` line in the log (``benchmarks/bench_startup.py`` reads them).
A plant with ``--colocate encoder`` runs the encoder too, under the encoder's
name (SIGUSR2: the encoder alone dies, for ``testbed run --kill encoder@S``).  SIGINT / SIGTERM, a ``Stop`` message, the loss of
the plant or the end of the run (+ grace) stop a node cleanly.

Exit codes: 0 stopped cleanly, 1 crashed (traceback on stderr), 2 bad scenario, a
different run configuration than the plant's or a Start of another protocol version
(``messages.PROTOCOL_VERSION``), 3 peers missing at startup.
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import os
import resource
import signal
import sys
import time
from typing import TYPE_CHECKING

from ..wire import transport
from ..wire.session import zenoh_config
from .context import NodeContext
from .options import NodeConfig, load_scenario
from .process import (
    on_stop_signals,
    parse_cpus,
    phase,
    set_realtime,
    setup_logging,
    tune_process,
)

if TYPE_CHECKING:
    from . import rerun_tap

log = logging.getLogger("testbed.nodes")

STOP_GRACE_S = 15.0  # a node still alive this long after SIGINT/SIGTERM exits hard


def _node_class(role: str):
    """The role's node class; only its module is imported (the attacker's needs no numba)."""
    import importlib

    module, name = {"plant": ("plant", "PlantNode"), "encoder": ("encoder", "EncoderNode"),
                    "attacker": ("attacker", "AttackerNode"), "controller": ("controller", "ControllerNode")}[role]
    return getattr(importlib.import_module(f"{__package__}.{module}"), name)


def _netns() -> str | None:
    try:
        return os.readlink("/proc/self/ns/net")
    except OSError:
        return None


def _refuse_protocol(role: str, ctx) -> int:
    """A Start of another protocol version came: one line naming both versions, exit 2."""
    print(f"testbed node {role}: refused: {ctx.protocol_refused}", file=sys.stderr)
    return 2


def run_node(cfg: NodeConfig) -> int:
    """Run one node process of configuration ``cfg`` to its end; its exit code."""
    import zenoh

    role = cfg.role
    setup_logging(role, cfg.verbose)
    phase(role, "up")
    if cfg.cpus:
        os.sched_setaffinity(0, parse_cpus(cfg.cpus))
    jf = None
    if cfg.scenario is None:  # TESTBED_JOIN: the configuration and the scenario from the join file
        from . import joined

        jf, cfg = joined.apply(cfg)
    opts = cfg.opts
    if role in opts.colocate:
        from ..common.errors import BadInput

        raise BadInput(f"--colocate {role}: the {role} runs inside the {opts.process_of(role)}'s process; "
                       f"start no {role} node")
    # the scenario text parsed and its plant, model and method built once (ScenarioError -> exit 2 in the CLI)
    if jf is None:
        assert cfg.scenario is not None  # else the join file gave jf
        sc = load_scenario(cfg.scenario, opts, check_design=not cfg.launched)
    else:
        sc = joined.scenario(jf, opts.overrides())
    phase(role, "scenario")
    tune_process(cfg.parent_pid)
    sys.setswitchinterval(1e-4)  # a callback thread waiting for the GIL waits 100 us, not 5 ms
    holder: dict = {}

    def on_signal(signum):  # on the signal thread: no lock of the main thread is held here
        ctx = holder.get("ctx")
        if ctx is not None:
            ctx.request_stop(f"signal {signal.Signals(signum).name}")

    def before_context(_signum):  # on the main thread: only while there is no context to stop
        if holder.get("ctx") is None:
            raise KeyboardInterrupt

    def kill_guest():  # SIGUSR2 (the launcher's --kill encoder@S with --colocate encoder)
        node = holder.get("node")
        if node is not None and hasattr(node, "kill_encoder"):
            node.kill_encoder()

    on_stop_signals(on_signal, main_handler=before_context, grace=STOP_GRACE_S,
                    others={signal.SIGUSR2: kill_guest} if "encoder" in opts.colocate and role == "plant" else None)
    assert cfg.session.run_id is not None  # a process's session has one (only the launcher's makes one)
    keys = transport.Keys.for_run(cfg.session.run_id)
    conf = zenoh_config(cfg.session, role, keys, hub=role == "plant" and not cfg.launched, colocate=opts.colocate)
    if cfg.session.insecure and not cfg.launched:
        print(f"testbed node {role}: INSECURE: no authentication, any local process can join run {cfg.session.run_id}",
              file=sys.stderr)
    code = 0
    cpu_info: dict = {}
    try:
        session_cm = zenoh.open(conf)
    except zenoh.ZError as e:
        print(f"testbed node {role}: no Zenoh session (the router is not there, or it refused the credentials): "
              f"{str(e).split(' at /')[0]}", file=sys.stderr)
        return 3
    with session_cm as session:
        phase(role, "session")
        ctx = NodeContext(role, session, sc, opts, keys)
        holder["ctx"] = ctx
        ctx.watch_collector = cfg.launched
        cfg = dataclasses.replace(cfg, wait_collector=cfg.wait_collector or cfg.launched)
        node = _node_class(role)(ctx, cfg)
        holder["node"] = node
        tap: rerun_tap.RerunTap | None = None
        guest_tap: rerun_tap.RerunTap | None = None
        try:
            if cfg.rerun_url or cfg.rerun_save:  # rerun's view (numpy, rerun) only when asked for
                from . import rerun_tap

                tap = rerun_tap.of(cfg, role, sc)
            if tap is not None:
                ctx.telemetry.tap = tap.put
            node.setup()
            guest = getattr(node, "encoder", None)
            if tap is not None and guest is not None:  # the colocated encoder's own stream (its part file)
                save = cfg.rerun_save and os.path.join(os.path.dirname(cfg.rerun_save), "encoder.rrd")
                guest_tap = rerun_tap.of(dataclasses.replace(cfg, rerun_save=save), "encoder", sc)
                if guest_tap is not None:
                    guest.ctx.telemetry.tap = guest_tap.put
            node.warmup()
            phase(role, "warm")
            # no cyclic-GC pauses in the loop (the loop makes no reference cycles worth collecting);
            # collected now, while the slower peers still start up
            gc.collect()
            gc.freeze()
            gc.disable()
            node.declare_alive()
            if not ctx.wait_for("alive", transport.ROLES, cfg.ready_timeout):
                if ctx.protocol_refused is not None:
                    return _refuse_protocol(role, ctx)
                if ctx.stop.is_set():
                    return 0
                print(f"testbed node {role}: peers not up after {cfg.ready_timeout:g} s: "
                      f"{', '.join(ctx.missing('alive', transport.ROLES))}", file=sys.stderr)
                return 3
            phase(role, "peers")
            # every peer's subscribers are declared (before its alive token): warm the publishers
            # now, while the others still start up, not in the lead before t0
            node.warm_publishers()
            node.declare_ready()
            phase(role, "ready")
            if role == "plant":
                st = node.start_run(cfg.start_lead, cfg.ready_timeout)
            else:
                st = ctx.wait_start(cfg.ready_timeout)
            if st is None:
                if ctx.protocol_refused is not None:
                    return _refuse_protocol(role, ctx)
                if ctx.stop_reason == "run mismatch":
                    print(f"testbed node {role}: the plant runs a different scenario or run options "
                          f"(digest mismatch)", file=sys.stderr)
                    return 2
                if ctx.stop.is_set():
                    return 0
                print(f"testbed node {role}: no start after {cfg.ready_timeout:g} s", file=sys.stderr)
                return 3
            phase(role, "start")
            log.info("%s: start, t0 = %d, %d samples of %g s", role, st.t0_ns, st.n_steps, st.T_ns / 1e9)
            rt = set_realtime(True) if cfg.realtime else False
            ru0, w0 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
            try:
                node.run()
            finally:
                if cfg.realtime:
                    set_realtime(False)
                gc.enable()
                ru1, w1 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
                cpu = (ru1.ru_utime + ru1.ru_stime) - (ru0.ru_utime + ru0.ru_stime)
                cpu_info = {"cpu_run_s": round(cpu, 3), "cpu_share": round(cpu / max(w1 - w0, 1e-9), 3),
                            "sched_fifo": rt}
        except Exception as e:  # noqa: BLE001 - reported below, exit code 1
            node.fail(e)
        phase(role, "end")
        guest = getattr(node, "encoder", None)
        published = [role]
        if guest is not None and not guest.killed:  # the colocated encoder's own account, under its name
            guest.ctx.telemetry.flush()
            gd = guest.summary()
            gd.update(guest.channel_summary())
            if guest_tap is not None:
                guest.ctx.telemetry.tap = None
                gd.update(guest_tap.close())
            gd.update(guest.ctx.telemetry.digest())
            gd["events_sent"], gd["events_suppressed"] = guest.ctx.events_sent, guest.ctx.events_suppressed
            gd.update(stop_reason=ctx.stop_reason if not guest.dead else "died", pid=os.getpid(), netns=_netns(),
                      error=None if guest.error is None else f"{type(guest.error).__name__}: {guest.error}")
            guest.ctx.publish_summary(gd)
            published.append(guest.ctx.role)
            guest.ctx.close()
        elif guest_tap is not None:
            guest_tap.close()
        ctx.telemetry.flush()
        data = node.summary()
        data.update(node.channel_summary())
        data.update(cpu_info)
        if tap is not None:
            ctx.telemetry.tap = None
            data.update(tap.close())
        data.update(ctx.telemetry.digest())
        data["events_sent"], data["events_suppressed"] = ctx.events_sent, ctx.events_suppressed
        data["stop_reason"] = ctx.stop_reason
        data["pid"] = os.getpid()
        data["netns"] = _netns()
        data["error"] = None if node.error is None else f"{type(node.error).__name__}: {node.error}"
        ctx.publish_summary(data)
        ctx.summary_received(published)  # a run's collector (if there is one) has them before the session closes
        ctx.close()
        phase(role, "closing")
        if node.error is not None:
            code = 1
    return code
