"""Traces for ``[attack] kind = "trace"``: the samples another run's attacker dropped, read from a
plain file of sample indices here, or from a recording by the reader the recording shells set.

A plain file holds dropped sample indices (one per line, or separated by spaces or commas) and
the header lines ``# T = 0.1`` (required: the period the trace was taken at) and ``# samples = 300``
(its length; default: the last index + 1).  A recording (``.mcap``) is read by the reader the caller
passes (``read_recording``): the scenario layer reads no MCAP itself, so the shells that load a scenario
(the commands, the launcher and its nodes, ``testbed.simulate``, campaigns) pass
``testbed.record.tracereader.read_recording_trace`` to ``testbed.scenario.load``, which hands it here.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

#: the largest plain trace file read (a million sample indices fit in well under this)
TRACE_FILE_MAX = 64 * 1024 * 1024

#: reads a recording's trace: path -> the ``[attack]`` parameters (``testbed.record.tracereader``)
RecordingTraceReader = Callable[[Path], dict]


def read_trace(path: str | Path, read_recording: RecordingTraceReader | None = None) -> dict:
    """The ``[attack]`` parameters of kind ``trace`` (``samples``, ``T``, ``n_samples``, ``source``)
    of a recording, read by ``read_recording`` (the samples its *attacker* dropped: not theta, which
    also counts withheld, late and invalid samples), or of a plain file of dropped sample indices."""
    p = Path(path)
    if p.suffix == ".mcap":
        if read_recording is None:
            raise ValueError("a recording is read as a trace by the testbed's commands and by testbed.simulate "
                             "(in a script of your own: testbed.scenario.load(..., read_recording_trace="
                             "testbed.record.tracereader.read_recording_trace)), or give a file of sample indices")
        return read_recording(p)
    size = p.stat().st_size
    if size > TRACE_FILE_MAX:
        raise ValueError(f"{size} bytes, more than a trace file may have ({TRACE_FILE_MAX} bytes)")
    T = None
    n = None
    samples = []
    for line in p.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if line.startswith("#"):
            key, _, val = line[1:].partition("=")
            if key.strip() == "T":
                T = float(val)
            elif key.strip() == "samples":
                n = int(val)
            continue
        for tok in line.replace(",", " ").split():
            samples.append(int(tok))
    if T is None:
        raise ValueError("no '# T = SECONDS' line (the period the trace was taken at)")
    return {"samples": samples, "T": T, "n_samples": n if n is not None else (max(samples) + 1 if samples else 0),
            "source": str(p)}
