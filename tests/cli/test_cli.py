"""The front door: one name per meaning across commands, old names still working, help and exit codes."""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess

import pytest
from helpers.cli import PY, SHARED, tb_here

from testbed import cli


def _parsers() -> dict[str, argparse.ArgumentParser]:
    ap = cli.build_parser()
    sub = next(a for a in ap._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def _options(p: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in p._actions for s in a.option_strings}





@pytest.mark.parametrize("flag", sorted(SHARED))
def test_every_command_has_the_shared_options_with_one_meaning(flag):
    parsers = _parsers()
    dests, metavars = set(), set()
    for name in SHARED[flag]:
        assert name in parsers, name
        opts = _options(parsers[name])
        assert flag in opts, f"testbed {name} has no {flag}"
        a = opts[flag]
        assert a.help and a.help != argparse.SUPPRESS, f"testbed {name} {flag}: no help line"
        dests.add(a.dest)
        metavars.add(a.metavar)
    assert len(dests) == 1, (flag, dests)
    if flag in ("--out", "--rrd", "--plot"):
        assert metavars == {{"--out": "PATH.mcap", "--rrd": "PATH.rrd", "--plot": "PATH.png"}[flag]}, metavars


def test_every_option_of_every_command_has_a_help_line():
    for name, p in _parsers().items():
        for a in p._actions:
            if a.option_strings and a.help is not argparse.SUPPRESS and a.dest != "help":
                assert a.help, f"testbed {name} {a.option_strings}: no help line"


def test_every_command_prints_its_help():
    """argparse formats help with ``%``: a literal percent sign must be written ``%%`` (``testbed campaign
    --help`` once ended in a traceback over "95 % Wilson")."""
    for name, p in _parsers().items():
        text = p.format_help()
        assert f"testbed {name}" in text, name


def test_old_names_are_hidden_aliases_of_the_new_ones():
    ps = _parsers()
    run = ps["run"]
    args = run.parse_args(["paper", "--record", "x.mcap", "--rerun-no-roa"])
    assert args.out == "x.mcap" and args.no_roa
    args = run.parse_args(["paper", "--out", "y.mcap", "--no-roa", "--rrd", "r.rrd"])
    assert args.out == "y.mcap" and args.no_roa and args.rrd == "r.rrd"
    helptext = run.format_help()
    assert not re.search(r"--record[ ,\]]", helptext) and "--rerun-no-roa" not in helptext


@pytest.mark.slow  # its own processes (an interpreter start-up each)
def test_help_has_no_markup_and_the_version_prints():
    r = subprocess.run([PY, "-m", "testbed.cli", "--help"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "``" not in r.stdout and "exit codes" in r.stdout
    r = subprocess.run([PY, "-m", "testbed.cli", "--version"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout.startswith("testbed (dos-testbed) ")


@pytest.mark.slow  # half a second or more on a warm cache
def test_scenarios_lists_descriptions_and_json(capsys):
    assert cli.main(["scenarios", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["scenarios"]
    assert {r["name"] for r in rows} >= {"paper", "paper-escape", "paper-greedy", "pendulum", "cartpole"}
    assert all(r["description"] for r in rows)
    assert cli.main(["scenarios"]) == 0
    assert "the paper's example" in capsys.readouterr().out


@pytest.mark.slow  # half a second or more on a warm cache
def test_simulate_plot_draws_fig_2(tmp_path, capsys):
    png = tmp_path / "fig2.png"
    assert cli.main(["simulate", "paper", "--plot", str(png), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["figure"] == str(png) and png.stat().st_size > 10_000


@pytest.mark.slow
def test_analyze_plot_is_a_file_path_and_a_folder_still_works(tmp_path):
    png = tmp_path / "an.png"
    assert cli.main(["analyze", "paper", "--plot", str(png), "--no-progress"]) == 0
    assert png.exists() and (tmp_path / "an-time-series.png").exists() and (tmp_path / "an-delta.png").exists()
    folder = tmp_path / "figs"
    assert cli.main(["analyze", "paper", "--plot", str(folder), "--no-progress"]) == 0
    assert (folder / "paper-allowable-region.png").exists()
    pdf = tmp_path / "an.pdf"
    assert cli.main(["analyze", "paper", "--plot", str(pdf), "--figsize", "column", "--no-progress"]) == 0
    assert pdf.read_bytes()[:5] == b"%PDF-" and (tmp_path / "an-delta.pdf").read_bytes()[:5] == b"%PDF-"


def test_a_figure_in_an_unknown_format_is_bad_input_before_any_work(tmp_path, capsys):
    assert cli.main(["analyze", "paper", "--plot", str(tmp_path / "an.jpg")]) == 2
    assert "a figure path ends in .png, .pdf, .svg" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())
    with pytest.raises(SystemExit) as e:
        cli.main(["simulate", "paper", "--plot", str(tmp_path / "a.gif")])
    assert e.value.code == 2 and "by the extension" in capsys.readouterr().err
    assert cli.main(["analyze", "paper", "--escape-x0", "0.3"]) == 2
    assert "--escape-x0 takes 'auto' or 2" in capsys.readouterr().err


@pytest.mark.slow  # its own processes (an interpreter start-up each)
def test_exit_codes_bad_input_is_2_with_one_line(tmp_path):
    cases = [
        ["simulate", "no-such-scenario"],
        ["simulate", "paper", "--duration", "-1"],
        ["report", str(tmp_path / "missing.mcap")],
        ["resimulate", str(tmp_path / "missing.mcap")],
        ["run", "paper", "--topology", "peer", "--secret-file", str(tmp_path / "x.secret")],  # certificates
        ["run", "paper", "--topology", "peer", "--listen", "tcp/127.0.0.1:7999"],  # a plain TCP endpoint
        ["run", "paper", "--topology", "router", "--tls-dir", str(tmp_path)],      # no certificate in it
        ["node", "plant", "paper", "--topology", "peer"],                          # no --tls-dir
        ["node", "plant", "paper", "--topology", "peer", "--tls-dir", str(tmp_path)],  # no certificate in it
        ["secret", "--tls", str(tmp_path)],                                        # never overwritten
    ]
    # in this process (testbed.cli.main, the entry point's function: about 1.3 s a case less); one case in a
    # process of its own, for the exit code a shell sees (``testbed run`` leaves through os._exit)
    for i, args in enumerate(cases):
        if i == 5:
            r = subprocess.run([PY, "-m", "testbed.cli", *args], capture_output=True, text=True, timeout=120)
            rc, err = r.returncode, r.stderr
        else:
            rc, _, err = tb_here(*args)
        assert rc == 2, (args, err)
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, (args, err)


@pytest.mark.slow  # the analysis of the paper's example: seconds of numerics
def test_the_theorem_2_verdict_does_not_read_as_a_contradiction(capsys):
    assert cli.main(["analyze", "paper", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "theorem2_holds=True" not in out and "within: False" not in out
    assert "does not cover it" in out


def test_exit_codes_come_from_one_definition_in_every_help_and_in_the_docs():
    """Every command's epilog and the table of docs/cli.md list the codes of ``errors.EXIT_CODES``
    (0, 1, 2 and 3), and no other code below 128."""
    from pathlib import Path

    from testbed.common.errors import EPILOG, EXIT_CODES

    assert sorted(EXIT_CODES) == [0, 1, 2, 3]
    helps = {"testbed": cli.build_parser().epilog, **{n: p.epilog for n, p in _parsers().items()}}
    for name, epilog in helps.items():
        assert epilog == EPILOG, name
        for code, meaning in EXIT_CODES.items():
            assert f"{code} {meaning}" in epilog, (name, code)
    doc = (Path(__file__).resolve().parents[2] / "docs" / "cli.md").read_text()
    section = doc.split("## Exit codes", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| (\d+) \|", section, flags=re.M)
    assert sorted(int(r) for r in rows) == sorted(EXIT_CODES), rows


@pytest.mark.parametrize("given", [None, "3"])
def test_a_post_mortem_command_runs_with_one_openblas_thread_unless_the_user_set_it(tmp_path, given):
    """``testbed report`` (and the other post-mortems) set ``OPENBLAS_NUM_THREADS=1`` before numpy loads, and keep
    the user's own value (docs/benchmarks.md: the pools' spin at their start)."""
    code = ("import atexit, os, sys\n"
            "atexit.register(lambda: print('threads', os.environ.get('OPENBLAS_NUM_THREADS')))\n"
            f"sys.argv = ['testbed', 'report', {str(tmp_path / 'missing.mcap')!r}]\n"
            "from testbed.cli import main\nmain()\n")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    r = subprocess.run([PY, "-c", code], capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr      # a missing file: one line, exit 2
    assert r.stdout.split() == ["threads", given or "1"], r.stdout
