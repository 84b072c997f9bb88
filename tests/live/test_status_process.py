"""A live run shows that it is alive (``testbed.live.status``): on a terminal one status line on stderr,
redrawn about once a second; on a pipe nothing unless ``--progress``; never anything on stdout.  And the
rule-of-thumb warnings of ``testbed run`` (``testbed.scenario.rulesofthumb``), said before the run."""

from __future__ import annotations

import json
import os
import pty
import re
import signal
import subprocess
import threading
from pathlib import Path

import pytest
from helpers.cli import TIMEOUT, tb_cmd
from helpers.live import live

pytestmark = pytest.mark.process

#: the docs' noisy example with no E_min and x0 on the corner of the first box (both rules of thumb broken)
NOISY = (Path(__file__).resolve().parents[2] / "docs" / "examples" / "paper-noisy.toml").read_text() \
    .replace("E0 = 0.12\n", "E0 = 0.1\n").replace("E_min = 3e-5\n", "").replace("duration = 45.0", "duration = 1.0")

STATUS = re.compile(r"sample (\d+)/(\d+) \| lost (\d+) \(attacker (\d+), channel (\d+), network (\d+), late (\d+), "
                    r"withheld (\d+)\) "
                    r"\| deadline misses (\d+) \| E_k enc (\S+), dec (\S+)")


def _statuses(text: str) -> list[re.Match]:
    return list(STATUS.finditer(text))


def _check_last(st: re.Match, s: dict) -> None:
    """The last status line is the run's end: every sample, and its losses those of the summary (the same
    function, ``recorded_losses``, counts both)."""
    k, N, lost, att, ch, net, late, wh, misses = (int(v) for v in st.groups()[:9])
    assert k == N == s["n_steps"], st.group(0)
    assert lost == sum(s["losses"].values()) == s["packets_dropped"], (st.group(0), s["losses"])
    got = {"attacker": att, "channel": ch, "network": net, "late": late, "withheld": wh}
    assert got == s["losses"], (st.group(0), s["losses"])
    assert misses == s["timing"]["deadline_misses"], (st.group(0), s["timing"])


def test_the_status_line_on_a_terminal(run_id):
    """stderr on a pseudo-terminal: the line is redrawn in place (carriage return, erase line) at least
    twice in a 3 s run; stdout (a pipe) holds the JSON summary alone."""
    master, slave = pty.openpty()
    cmd = tb_cmd("run", "paper", "--duration", "3", "--no-record", "--json", "--run-id", run_id)
    p = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=slave,
                         start_new_session=True)
    os.close(slave)
    chunks: list[bytes] = []

    def read():
        while True:
            try:
                b = os.read(master, 4096)
            except OSError:  # EIO: every holder of the terminal's other end has closed it
                return
            if not b:
                return
            chunks.append(b)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        out, _ = p.communicate(timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        p.communicate()
        pytest.fail("testbed run did not finish")
    finally:
        reader.join(10)
        os.close(master)
    err = b"".join(chunks).decode(errors="replace")
    assert p.returncode == 0, err[-3000:]
    s = json.loads(out)
    sts = _statuses(err)
    assert len(sts) >= 2, err
    assert err.count("\r\x1b[K") >= 2, err   # redrawn in place
    _check_last(sts[-1], s)
    assert b"sample " not in out and b"\x1b" not in out


def test_progress_on_a_pipe_and_nothing_without_it(run_id, tmp_path):
    """``--progress`` on a pipe: a line per update, plain text, and the last one is the run's end; without it
    a pipe gets no status line.  The second run, a noisy sensor with no E_min and x0 on the corner of the first
    box, is warned about both before it runs."""
    rc, s, err = live(run_id, "paper", "--duration", "3", "--no-record", "--progress")
    assert rc == 0, err[-3000:]
    lines = [ln for ln in err.splitlines() if ln.startswith("sample ")]
    assert len(lines) >= 2 and all(STATUS.fullmatch(ln) for ln in lines), err
    assert "\x1b" not in err and "\r" not in err
    _check_last(_statuses(lines[-1])[0], s)

    path = tmp_path / "noisy.toml"
    assert "E_min" not in NOISY.split("[quantizer]")[1].split("[controller]")[0] and "duration = 1.0" in NOISY
    path.write_text(NOISY)
    rc, s, err = live(run_id + "b", path, "--no-record")
    assert rc in (0, 1), err[-3000:]
    assert not _statuses(err), err
    warned = [ln for ln in err.splitlines() if ln.startswith("testbed run: warning: ")]
    assert len(warned) == 2 and "E_min" in warned[0] and "E0" in warned[1], err
