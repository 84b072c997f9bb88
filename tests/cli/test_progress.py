"""The progress bar of the long commands (``testbed/common/progress.py``): on stderr only; off a terminal the
plain lines of a log (a tenth of the work each; a campaign's every 5 s and at its end), on a terminal
tqdm's bar drawn in place (a real pseudo-terminal), a campaign's starting after its first run."""

import fcntl
import os
import pty
import select
import struct
import subprocess
import sys
import termios
from pathlib import Path

import testbed
from testbed.common.progress import Progress, RunsProgress

ROOT = str(Path(testbed.__file__).resolve().parent.parent)


def test_off_a_terminal_plain_lines_on_stderr_only(capsys):
    p = Progress("sweep")
    for i in range(21):
        p(i, 20)
    out, err = capsys.readouterr()
    lines = err.splitlines()
    assert out == "" and len(lines) == 11, lines   # one a tenth, and the end
    assert lines[0].startswith("sweep [                              ] 0/20") and ", ETA" in lines[5]
    assert lines[-1].startswith("sweep [##############################] 20/20") and "ETA" not in lines[-1]
    r = RunsProgress(4, 1)
    r.say("4 runs in out, 1 found done; 3 to run")
    r(1, 0)
    r(2, 0)      # within 5 s of the last line: none
    r(4, 1, final=True)
    out, err = capsys.readouterr()
    lines = err.splitlines()
    assert out == "" and lines[0] == "campaign: 4 runs in out, 1 found done; 3 to run", lines
    assert lines[1].startswith("campaign: 1/4 runs done, 0 failed, 3 left, ") and len(lines) == 3
    assert lines[2].startswith("campaign: 4/4 runs done, 1 failed, 0 left, ")


SCRIPT = """
from testbed.common.progress import Progress, RunsProgress
p = Progress("sweep")
for i in range(11):
    p(i, 10)
r = RunsProgress(5, 0)
r.say("5 runs; 5 to run")
r(0, 0)
for d in range(1, 6):
    r(d, 0)
r(5, 0, final=True)
print("RESULT")
"""


def test_on_a_terminal_tqdm_draws_the_bar():
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 30, 100, 0, 0))
    env = {**os.environ, "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}
    p = subprocess.Popen([sys.executable, "-c", SCRIPT], stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                         stderr=slave, env=env)
    os.close(slave)
    err = b""
    while True:
        ready, _, _ = select.select([master], [], [], 60)
        if not ready:
            break
        try:
            chunk = os.read(master, 65536)
        except OSError:  # the child closed its end
            break
        if not chunk:
            break
        err += chunk
    out = p.communicate(timeout=60)[0]
    os.close(master)
    text = err.decode().replace("\r", "\n")
    assert out == b"RESULT\n"                                     # the result alone on stdout
    assert "sweep: 100%" in text and "10/10 [" in text, text      # tqdm's bar, with elapsed<left
    assert "campaign: 5 runs; 5 to run" in text
    assert "campaign:  20%" in text and "1/5 [" in text, text     # the bar starts at the first run's end
    assert "campaign:   0%" not in text and "0/5 [" not in text
    assert "5/5 runs done, 0 failed, 0 left" in text
