"""A run option is defined once (``testbed.common.optionspec``): the parsers of ``testbed run``, ``node``, ``record`` and
``conformance``, the typed configurations, a node's command line, the join file and the options table of
docs/cli.md are generated from that one definition, and agree.  And the public-CLI contract: a process the testbed
starts is a ``testbed`` subcommand, started with the flags a user would type (docs/development.md)."""

from __future__ import annotations

import argparse
import ast
import dataclasses
import json
import re
from pathlib import Path

import pytest

import testbed
from testbed import cli
from testbed.commands import conformance as conformance_cmd
from testbed.commands.liveconfig import node_config, recorder_config, run_config, run_options, session_options
from testbed.common import optionspec
from testbed.nodes import optionsdoc
from testbed.nodes.options import NodeConfig, RecorderConfig, RunConfig, RunOptions, load_scenario, run_digest
from testbed.wire.session import SessionOptions

ROOT = Path(testbed.__file__).resolve().parent
COMMANDS = ("run", "node", "record", "conformance")
CLASSES = (RunOptions, SessionOptions, RunConfig, NodeConfig, RecorderConfig)
#: the positional arguments each command needs before its options
POSITIONAL = {"run": ["paper"], "node": ["plant", "paper"], "record": ["paper"], "conformance": []}
#: a value of each ROLE=VALUE / ROLE@VALUE form, by metavar
PAIRS = {"ROLE=ENDPOINT": "plant=tcp/10.0.0.2:0", "ROLE=COMMAND": "plant=nice", "WHO=CPUS": "plant=1",
         "ROLE@SECONDS": "plant@1.5", "ROLE@K": "controller@3", "ROLE@SECONDS:DURATION": "plant@1:0.5"}


def _parser(command: str) -> argparse.ArgumentParser:
    """The public parser of ``command``, as ``testbed.cli`` builds it (conformance: the parser of its options, which
    it reads after SCENARIO)."""
    if command == "conformance":
        p = argparse.ArgumentParser()
        conformance_cmd._add_options(p)
        return p
    sub = next(a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[command]


def _parse(command: str, argv: list[str]):
    return _parser(command).parse_args([*POSITIONAL[command], *argv])


def _sample(f, o) -> str:
    """A value of the option unlike its default."""
    if o.metavar in PAIRS:
        return PAIRS[o.metavar]
    if o.choices:
        d = optionspec.default_of(f, o)
        return next(c for c in reversed(o.choices) if c != d)
    if o.kind is int:
        return "7"
    if o.kind is float:
        return "0.375"
    return "x-" + f.name


def _argv(f, o) -> list[str]:
    flag = optionspec.flag_of(f, o)
    return [flag] if o.switch else [flag, _sample(f, o)]


def _config(command: str, cls, args):
    """The typed configuration ``command`` builds from its parsed arguments, where ``cls``'s fields are."""
    if command == "run":
        cfg = run_config(args)
        return {RunOptions: cfg.opts, SessionOptions: cfg.session, RunConfig: cfg}[cls]
    if command == "node":
        cfg = node_config(args)
        return {RunOptions: cfg.opts, SessionOptions: cfg.session, NodeConfig: cfg}[cls]
    if command == "record":
        cfg = recorder_config(args)
        return {RunOptions: cfg.opts, SessionOptions: cfg.session, RecorderConfig: cfg}[cls]
    return {RunOptions: lambda: run_options(args, "conformance"),
            SessionOptions: lambda: session_options(args, "conformance"),
            RunConfig: lambda: args}[cls]()  # conformance reads its one RunConfig option (--startup-timeout) itself


CASES = [(cls, f.name, c) for cls in CLASSES for f, o in optionspec.options(cls) for c in COMMANDS if c in o.commands]


@pytest.mark.parametrize(("cls", "name", "command"), CASES, ids=[f"{c.__name__}.{n}-{m}" for c, n, m in CASES])
def test_every_command_that_receives_an_option_parses_it_into_its_config(cls, name, command):
    f, o = next((f, o) for f, o in optionspec.options(cls, command) if f.name == name)
    args = _parse(command, _argv(f, o))
    value = getattr(_config(command, cls, args), name)
    default = optionspec.default_of(f, o)
    assert value != default and value not in ((), {}, None), (name, command, value)
    if o.switch:
        assert value is True
    elif o.convert is None and not isinstance(f.default, tuple):
        assert value == (o.kind or str)(_sample(f, o))


@pytest.mark.parametrize("command", COMMANDS)
def test_each_default_is_written_once(command):
    """Nothing given: the configuration a command builds is the dataclass's own default (per command where the
    definition says so: ``testbed run``'s topology auto)."""
    args = _parse(command, [])
    if command == "node":
        assert node_config(args) == NodeConfig(role="plant", scenario="paper")
    elif command == "record":
        assert recorder_config(args) == RecorderConfig(scenario="paper")
    elif command == "run":
        cfg = run_config(args)
        assert dataclasses.replace(cfg, json=False) == RunConfig(scenario="paper")
        assert cfg.topology == "auto" and cfg.run_id is None and cfg.listen is None
    else:
        assert session_options(args, "conformance") == SessionOptions.of("run")
        assert args.startup_timeout == RunConfig.__dataclass_fields__["startup_timeout"].default
    assert SessionOptions().topology == "router" and NodeConfig("plant", None).session.topology == "router"


def _everything(command: str, cls):
    """``cls``'s configuration with every option of ``command`` set away from its default, by its flags."""
    argv = [a for c in (RunOptions, SessionOptions, cls) for f, o in optionspec.options(c, command)
            if not (c is RunOptions and f.name == "colocate" and command == "record") for a in _argv(f, o)]
    return argv


@pytest.mark.parametrize(("command", "cls", "build"), [("node", NodeConfig, node_config),
                                                        ("record", RecorderConfig, recorder_config)])
def test_a_process_config_round_trips_through_its_public_command_line(command, cls, build):
    """config -> argv -> ``testbed COMMAND``'s parser built by ``testbed.cli`` -> the same config: a node the
    launcher starts is started exactly as a user would start it by hand."""
    cfg = build(_parse(command, _everything(command, cls)))
    for c, part in ((RunOptions, cfg.opts), (SessionOptions, cfg.session), (cls, cfg)):
        for f, o in optionspec.options(c, command):
            if not (c is RunOptions and f.name == "colocate" and command == "record"):
                assert getattr(part, f.name) != optionspec.default_of(f, o), f.name  # every option is exercised
    argv = cfg.argv()
    assert argv[0] == command
    assert build(cli.build_parser().parse_args(argv)) == cfg
    plain = cls(**({"role": "controller", "scenario": None} if cls is NodeConfig else {"scenario": "paper"}))
    assert build(cli.build_parser().parse_args(plain.argv())) == plain


def test_the_launchers_session_is_testbed_runs_flags():
    """conformance hands ``testbed run`` its network as the flags of ``testbed run`` (``SessionOptions.argv("run")``)."""
    s = session_options(_parse("conformance", ["--listen", "tls/127.0.0.1:9", "--tls-dir", "/x", "--topology", "peer",
                                               "--low-latency", "--zenoh-config", "z.json5"]), "conformance")
    again = run_config(_parse("run", s.argv("run")))
    assert again.session == s and again.listen == "tls/127.0.0.1:9"


def test_the_join_file_carries_every_run_option_a_node_needs():
    """The join file's ``run_options`` (``RunOptions.join_fields``, through JSON) gives an external node the run's
    options: every option a node takes, each run digest option among them."""
    f_by = {f.name: (f, o) for f, o in optionspec.options(RunOptions, "node")}
    full = optionspec.from_args(RunOptions, _parse("node", [a for f, o in f_by.values() for a in _argv(f, o)]),
                                "node")
    carried = json.loads(json.dumps(full.join_fields()))
    assert set(carried) == set(f_by)
    assert {f.name for f, o in optionspec.options(RunOptions) if o.digest} <= set(carried)
    assert RunOptions.of_join(carried) == full
    assert RunOptions.of_join(json.loads(json.dumps(RunOptions().join_fields()))) == RunOptions()
    from testbed.common.errors import BadInput

    with pytest.raises(BadInput, match="unknown run option 'speed'"):
        RunOptions.of_join({"speed": 2})


def test_every_digest_option_enters_the_run_digest():
    """An option marked ``digest`` changes the start digest when it changes (nodes that disagree are refused)."""
    base_opts = RunOptions()
    base = run_digest(load_scenario("paper", base_opts), base_opts)
    values = {"duration": 12.0, "T": 0.05, "timing": "physical", "deadline": 0.4, "mode": "ideal",
              "loss_fraction": 0.6, "actuation": "arrival", "rule": "delay-aware", "method": "zoom",
              "ack_via_attacker": True, "separate_ack": True, "colocate": ("encoder",)}
    digest = {f.name for f, o in optionspec.options(RunOptions) if o.digest}
    assert digest == set(values)  # a new digest option: add its value here
    for name, v in values.items():
        opts = dataclasses.replace(base_opts, **{name: v})
        assert run_digest(load_scenario("paper", opts), opts) != base, name
    # and one that is not marked does not: --seed (only the attacker draws from the attack)
    seeded = RunOptions(seed=11)
    assert run_digest(load_scenario("cartpole", seeded), seeded) == run_digest(load_scenario("cartpole", base_opts),
                                                                              base_opts)


def test_the_docs_options_table_is_generated():
    text = optionsdoc.DOC.read_text(encoding="utf-8")
    assert "<!-- BEGIN generated:options -->" in text
    assert optionsdoc.render(text) == text, "regenerate: python -m testbed.nodes.optionsdoc"
    for cls in CLASSES:  # every visible option has its row
        for f, o in optionspec.options(cls):
            if not o.hidden and set(o.commands) & set(COMMANDS):
                assert f"`{optionspec.flag_of(f, o)}" in text or f"`{o.short}, {optionspec.flag_of(f, o)}" in text


# ---------------------------------------------------------------------------- the public-CLI contract
def _spawned_modules():
    """Every ``[..., "-m", MODULE, NEXT, ...]`` list or tuple literal in testbed/'s source: (file, line, MODULE, NEXT)."""
    for path in sorted(ROOT.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.List, ast.Tuple)):
                elts = node.elts
                for i, e in enumerate(elts[:-1]):
                    if isinstance(e, ast.Constant) and e.value == "-m":
                        nxt = elts[i + 2] if i + 2 < len(elts) else None
                        yield path.relative_to(ROOT.parent), e.lineno, elts[i + 1], nxt


@pytest.mark.slow  # half a second or more on a warm cache
def test_the_testbed_starts_only_testbed_subcommands():
    """A process the testbed starts (a node, the recorder, a run of a campaign, of conformance or versus) is
    ``python -m testbed.cli SUBCOMMAND``: the public command line, never a module of its own."""
    found = list(_spawned_modules())
    assert len(found) >= 5  # the launcher, the recorder, conformance, campaign rows, versus
    for where, line, module, nxt in found:
        assert isinstance(module, ast.Constant) and module.value == "testbed.cli", f"{where}:{line}"
        assert (isinstance(nxt, ast.Constant) and nxt.value in cli.COMMANDS) or isinstance(nxt, ast.Starred), \
            f"{where}:{line}: not a testbed subcommand"


# ---------------------------------------------------------------------------- no module global patched at run time
def _module_names(tree) -> set[str]:
    """The names a module binds to the testbed's modules (``import testbed.x as y``, ``from . import x``)."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {(a.asname or a.name).split(".")[0] for a in node.names if a.name.startswith("testbed")}
        elif isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("testbed")):
            names |= {a.asname or a.name for a in node.names if a.name[:1].islower()}
    return names


@pytest.mark.slow  # half a second or more on a warm cache
def test_no_module_sets_another_modules_global():
    """A dependency is passed, never patched into another of the testbed's modules (``traces.recording_trace_reader``
    was): no ``module.NAME = ...`` anywhere in testbed/."""
    found = []
    for path in sorted(ROOT.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        mods = _module_names(tree)
        for node in ast.walk(tree):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(
                node, (ast.AugAssign, ast.AnnAssign)) else []
            for t in targets:
                if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id in mods:
                    found.append(f"{path.relative_to(ROOT.parent)}:{node.lineno}: {t.value.id}.{t.attr}")
    assert found == []


def test_a_recording_trace_is_read_by_the_reader_the_caller_passes(tmp_path):
    """``testbed.scenario`` reads a recording named as a trace with the reader it is given, and says what to pass
    when none is; a plain trace file needs none."""
    from testbed import scenario
    from testbed.common.errors import BadInput
    from testbed.scenario import traces

    assert not hasattr(traces, "recording_trace_reader")
    seen = []

    def reader(p):
        seen.append(Path(p).name)
        return {"samples": [2, 3], "T": 0.1, "n_samples": 300, "source": str(p)}

    base = scenario.load("paper").source
    text = re.sub(r'kind = "intervals"\nintervals = .*\n', 'kind = "trace"\nsource = "other.mcap"\n', base)
    assert 'source = "other.mcap"' in text
    with pytest.raises((BadInput, ValueError), match="read_recording_trace"):
        scenario.loads(text, base_dir=tmp_path)
    sc = scenario.loads(text, base_dir=tmp_path, read_recording_trace=reader)
    assert seen == ["other.mcap"] and list(sc.attack.params_dict["samples"]) == [2, 3]
    again = scenario.with_overrides(sc, {"duration": 12.0})  # the trace as read: not read a second time
    assert seen == ["other.mcap"] and list(again.attack.params_dict["samples"]) == [2, 3] and again.n_steps == 120
