"""The typed configuration of a live run: built once from the command line, handed to each process as flags,
and rebuilt there to the same value (what the launcher means is what the node runs)."""

from __future__ import annotations

import argparse
import dataclasses
import shutil
from pathlib import Path

import pytest
from helpers.cli import tb_run_here

from testbed.commands.liveconfig import node_config, recorder_config, run_config
from testbed.nodes.options import NodeConfig, RecorderConfig, RunOptions
from testbed.wire.session import SessionOptions

OPTS = RunOptions(duration=2.5, T=0.05, timing="physical", deadline=0.4, mode="ideal", loss_fraction=0.7,
                  actuation="arrival", rule="delay-aware", seed=7, method="paper", ack_via_attacker=True,
                  separate_ack=True, colocate=("encoder",))
SESSION = SessionOptions(run_id="r-1", listen=("tls/127.0.0.1:0",), connect=("tls/127.0.0.1:7447",),
                         zenoh_config="/x/z.json5", topology="peer", tls_dir="/x/tls", low_latency=True)


def _parse(module: str, name: str, argv: list[str]):
    import importlib

    from testbed.common.dispatch import add_command_arguments

    p = argparse.ArgumentParser()
    add_command_arguments(p, importlib.import_module(module), name)
    return p.parse_args(argv)


def test_a_node_config_survives_its_command_line():
    """Every field set away from its default: ``argv`` and ``testbed node``'s parser give the same ``NodeConfig``."""
    cfg = NodeConfig(role="plant", scenario="paper", opts=OPTS, session=SESSION, ready_timeout=33.5, realtime=True,
                     cpus="0,1", rx="spin", rx_spin_us=250.0, parent_pid=4242, launched=True, crash_at=9,
                     verbose=True, rerun_url="rerun+http://127.0.0.1:9876/proxy", rerun_save="/x/plant.rrd",
                     recording_id="rec", wait_collector=True, start_lead=0.35, spin_us=120.0, encoder_crash_at=4,
                     ack_grace=0.3, corrupt="3:range")
    for f in dataclasses.fields(NodeConfig):  # the test covers every field
        assert getattr(cfg, f.name) != f.default or f.name in ("role", "scenario"), f.name
    argv = cfg.argv()
    assert argv[:3] == ["node", "plant", "paper"]
    assert node_config(_parse("testbed.commands.node", "node", argv[1:])) == cfg
    plain = NodeConfig(role="controller", scenario=None)  # a node of a join file: no scenario, defaults
    assert node_config(_parse("testbed.commands.node", "node", plain.argv()[1:])) == plain


def test_a_recorder_config_survives_its_command_line():
    cfg = RecorderConfig(scenario="paper", opts=dataclasses.replace(OPTS, colocate=()),
                         session=dataclasses.replace(SESSION, topology="router", tls_dir=None, listen=(),
                                                     secret_file="/x/recorder.secret"),
                         out="/x/run.mcap", force=True, loop="on", flush=0.25, linger=3.0, nice=5, cpus="1",
                         parent_pid=17, launched=True, scenario_ref="paper", verbose=True)
    assert cfg.argv()[:2] == ["record", "paper"]
    assert recorder_config(_parse("testbed.commands.record", "record", cfg.argv()[1:])) == cfg


def test_the_launcher_gives_each_process_its_part_of_the_run_config():
    """``testbed run``'s flags -> one ``RunConfig`` -> each node's ``NodeConfig`` (what its command line carries)."""
    from testbed.live.launcher import STARTUP_GRACE_S, Launcher

    args = _parse("testbed.commands.run", "run", [
        "paper", "--no-record", "--duration", "2", "--colocate", "encoder", "--crash", "controller@5",
        "--crash", "encoder@4", "--corrupt", "3", "--spin-us", "50", "--ack-grace", "0.3", "--rx", "spin",
        "--rx-spin-us", "80", "--cpu", "attacker=0", "--realtime", "--startup-timeout", "40", "--low-latency"])
    cfg = run_config(args)
    assert cfg.crash == {"controller": 5, "encoder": 4} and cfg.cpu == {"attacker": "0"}
    la = Launcher(cfg)
    try:
        nodes = {r: la.node_config(r) for r in la.processes}
        assert set(nodes) == {"plant", "attacker", "controller"}  # the encoder runs in the plant's process
        for n in nodes.values():
            assert n.opts == la.opts and n.opts.duration == 2.0 and n.launched and n.realtime
            assert n.ready_timeout == 40.0 + STARTUP_GRACE_S and n.rx == "spin" and n.rx_spin_us == 80.0
            assert n.session.run_id == la.run_id and n.session.connect == (la.creds.node_connect,)
            assert n.session.topology == la.creds.topology and n.session.low_latency
            assert n.scenario == la.scenario_ref
        assert nodes["plant"].spin_us == 50.0 and nodes["plant"].encoder_crash_at == 4
        assert nodes["plant"].ack_grace == 0.3  # the encoder's grace goes to the process that runs it
        assert nodes["controller"].crash_at == 5 and nodes["controller"].spin_us is None
        assert nodes["attacker"].corrupt == "3" and nodes["attacker"].cpus == "0" and nodes["plant"].corrupt is None
        cmd = la.command("attacker")
        assert cmd[cmd.index("testbed.cli") + 1:] == nodes["attacker"].argv()
    finally:
        if la.own_dir:
            shutil.rmtree(la.run_dir, ignore_errors=True)


@pytest.mark.parametrize("flags, T, fifo", [
    ([], 0.002, "permitted"),               # auto: a fast loop, where this process may
    ([], 0.1, False),                       # auto: a slow loop stays SCHED_OTHER
    (["--realtime"], 0.1, True),            # --realtime alone is on, whatever T
    (["--realtime", "on"], 0.1, True),
    (["--realtime", "off"], 0.002, False),
    (["--realtime", "auto"], 0.002, "permitted"),
])
def test_realtime_is_read_once_as_on_off_or_auto_by_the_loops_period(flags, T, fifo):
    """``--realtime`` [auto|on|off]: ``RunConfig.sched_fifo(T)`` is the one reading of it, the nodes' ``realtime``
    and the router's priority follow it (auto: on below ``FAST_T`` where SCHED_FIFO is permitted)."""
    from testbed.nodes.options import FAST_T
    from testbed.nodes.process import fifo_permitted

    cfg = run_config(_parse("testbed.commands.run", "run", ["paper", "--no-record", *flags]))
    assert cfg.realtime == (flags[1] if len(flags) > 1 else "on" if flags else "auto")
    want = fifo_permitted() if fifo == "permitted" else fifo
    assert cfg.sched_fifo(T) is want
    assert T < FAST_T or not cfg.sched_fifo(T) or cfg.realtime == "on"


@pytest.mark.parametrize("flags, says", [
    (["--kill", "plant@soon"], "--kill: 'soon' is not a number"),
    (["--kill", "plant@nan"], "--kill: 'nan' is not a finite number >= 0"),
    (["--crash", "controller@-3"], "--crash: '-3' is not a finite number >= 0"),
    (["--crash", "plant"], "--crash must be ROLE@VALUE"),
    (["--cpu", "nobody=1"], "--cpu must be ROLE=VALUE"),
    # a fault the 3 s run never reaches is refused, not silently skipped
    (["--duration", "3", "--stall", "controller@20:1"], "--stall controller@20:1: 20 s is past the run's end"),
    (["--duration", "3", "--stall", "controller@3:1"], "--stall controller@3:1: 3 s is past the run's end"),
    (["--duration", "3", "--kill", "plant@7.5"], "--kill plant@7.5: 7.5 s is past the run's end"),
    (["--duration", "3", "--cut", "plant@4:1"], "--cut plant@4:1: 4 s is past the run's end"),
    (["--duration", "3", "--crash", "encoder@30"], "--crash encoder@30: sample 30 is past the run's last sample (29)"),
])
def test_a_malformed_run_flag_is_one_line_and_exit_2(flags, says):
    r = tb_run_here("run", "paper", "--no-record", *flags)  # refused before any process starts
    assert r.returncode == 2 and says in r.stderr and r.stderr.strip().count("\n") == 0, r.stderr


def test_the_run_digest_covers_the_method_reference_params_and_module(tmp_path):
    """Every node must agree on the method: its reference and params (a --method swap too) and the sha256
    of its module's source enter the digest, as the plant module's does; the same scenario gives the same."""
    from testbed import scenario
    from testbed.nodes.options import run_digest

    examples = Path(__file__).resolve().parents[2] / "docs" / "examples"
    for f in ("mymethod.py", "mymethod.toml"):
        shutil.copy(examples / f, tmp_path / f)
    opts = RunOptions()
    sc = scenario.load(tmp_path / "mymethod.toml")
    d0 = run_digest(sc, opts)
    assert run_digest(scenario.load(tmp_path / "mymethod.toml"), opts) == d0
    assert run_digest(scenario.with_overrides(sc, {"method": "paper"}), opts) != d0
    assert run_digest(scenario.with_overrides(sc, {"method": {"params": {"a": 0.9}}}), opts) != d0
    # the same reference and params, the module's source changed (a comment): another digest
    other = tmp_path / "other"
    other.mkdir()
    (other / "mymethod.toml").write_text((tmp_path / "mymethod.toml").read_text())
    (other / "mymethod.py").write_text((tmp_path / "mymethod.py").read_text() + "\n# edited\n")
    sc2 = scenario.load(other / "mymethod.toml")
    assert sc2.source == sc.source and sc2.method.name == sc.method.name
    assert run_digest(sc2, opts) != d0
