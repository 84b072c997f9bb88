"""The reader of a recording as an attack trace, importable at no cost: the shells that load scenarios pass it to
``testbed.scenario`` (``read_recording_trace=``), which reads no MCAP itself (``testbed.scenario.traces``)."""

from __future__ import annotations

from pathlib import Path


def read_recording_trace(path: str | Path) -> dict:
    """``testbed.record.trace.read_recording_trace``, its readers (numpy, mcap) loaded on first use."""
    from .trace import read_recording_trace as read

    return read(path)
