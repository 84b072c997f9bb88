"""The ``testbed`` command in a test: in its own process (``tb``, ``tb_run``, ``run_cli``: what a user's shell
does, exit code and all) or in this one (``tb_here``, ``tb_run_here``: ``testbed.cli.main``, for a test of a
command's output that is not about its process), and the options every command shares (``SHARED``)."""

from __future__ import annotations

import contextlib
import io
import os
import signal
import subprocess
import sys

import pytest

PY = sys.executable
TIMEOUT = float(os.environ.get("TESTBED_PROCESS_TIMEOUT", "300"))  # JIT warm-up of 4 nodes on 2 cores


def tb_cmd(*args) -> list[str]:
    return [PY, "-m", "testbed.cli", *args]


def run_cli(cmd: list[str], timeout: float = TIMEOUT, *, cwd=None, env: dict | None = None):
    """``cmd`` in its own process group (``env`` added to this process's environment): (exit code, stdout,
    stderr); past ``timeout`` the group is killed and the test fails."""
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         cwd=cwd, env=None if env is None else {**os.environ, **env})
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        out, err = p.communicate()
        pytest.fail(f"{' '.join(cmd)} did not finish in {timeout} s\n{err[-3000:]}")
    return p.returncode, out, err


def tb(*args, cwd=None, env: dict | None = None, timeout: float = TIMEOUT) -> tuple[int, str, str]:
    """``testbed ARGS`` in its own process, in ``cwd``: (exit code, stdout, stderr)."""
    return run_cli(tb_cmd(*map(str, args)), timeout, cwd=cwd, env=env)


def tb_run(*args, cwd=None, env: dict | None = None, timeout: float = TIMEOUT) -> subprocess.CompletedProcess:
    """:func:`tb` as a ``subprocess.CompletedProcess`` (``returncode``, ``stdout``, ``stderr``)."""
    rc, out, err = tb(*args, cwd=cwd, env=env, timeout=timeout)
    return subprocess.CompletedProcess(tb_cmd(*map(str, args)), rc, out, err)


def _stream() -> io.TextIOWrapper:
    """A text stream with a byte buffer under it, not a terminal (a command writes what it writes to a pipe)."""
    return io.TextIOWrapper(io.BytesIO(), encoding="utf-8", newline="\n", write_through=True)


def _text(stream: io.TextIOWrapper) -> str:
    stream.flush()
    return stream.buffer.getvalue().decode("utf-8", errors="replace")


def tb_here(*args, cwd=None, env: dict | None = None) -> tuple[int, str, str]:
    """``testbed ARGS`` in this process (``testbed.cli.main``, the entry point's own function): (exit code,
    stdout, stderr) as :func:`tb` gives them, without a new interpreter (a process pays about 1.3 s of start-up
    and kernel loading).  For a test of what a command prints, computes or writes, not of its process (its
    signals, its start-up imports, a module of the user's loaded fresh): those keep :func:`tb`.  ``cwd`` and
    ``env`` (added to the environment) hold for the call and are restored after it."""
    from testbed import cli

    out, err = _stream(), _stream()
    old_cwd, old_env = os.getcwd(), dict(os.environ)
    try:
        if cwd is not None:
            os.chdir(cwd)
        os.environ.update({k: str(v) for k, v in (env or {}).items()})
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                rc = cli.main([str(a) for a in args])
            except SystemExit as e:  # argparse: --help, a usage error
                if e.code is None or isinstance(e.code, int):
                    rc = e.code or 0
                else:
                    print(e.code, file=sys.stderr)
                    rc = 1
    finally:
        os.chdir(old_cwd)
        os.environ.clear()
        os.environ.update(old_env)
    return rc, _text(out), _text(err)


def tb_run_here(*args, cwd=None, env: dict | None = None) -> subprocess.CompletedProcess:
    """:func:`tb_here` as a ``subprocess.CompletedProcess`` (``returncode``, ``stdout``, ``stderr``)."""
    rc, out, err = tb_here(*args, cwd=cwd, env=env)
    return subprocess.CompletedProcess(["testbed", *map(str, args)], rc, out, err)


#: the shared options and the commands that must have them (docs/cli.md)
SHARED = {
    "--json": ["scenarios", "simulate", "run", "report", "replay", "analyze", "roa", "sweep", "resimulate",
               "plants", "check-plant", "worst-attack", "vulnerability", "secret", "compare", "noise"],
    "--out": ["run", "simulate", "record"],
    "--rrd": ["run", "simulate", "replay"],
    "--plot": ["simulate", "analyze", "roa", "sweep", "report", "vulnerability", "compare", "noise", "campaign"],
    "--figsize": ["simulate", "analyze", "roa", "sweep", "report", "vulnerability", "compare", "noise", "campaign"],
    "--no-roa": ["run", "simulate", "replay"],
    "--no-progress": ["analyze", "roa", "sweep", "worst-attack", "vulnerability", "noise"],
    "--workers": ["analyze", "roa", "sweep", "worst-attack", "vulnerability"],
}
