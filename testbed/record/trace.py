"""A recording read as an attack trace: the samples its attacker dropped (``testbed.scenario.traces``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .columns import read_columns, read_metadata
from .recorded import recorded_scenario


def read_recording_trace(path: str | Path) -> dict:
    """The ``[attack]`` parameters of kind ``trace`` of a recording: the samples its *attacker*
    dropped (not theta, which also counts withheld, late and invalid samples), its T and length."""
    p = str(path)
    meta, _ = read_metadata(p)
    rsc, _ps, _ms = recorded_scenario(meta, p, note=False)  # the attacker's log needs no code
    cols = read_columns(p, fields={"attacker.dropped"}, sc=rsc)
    has = cols.has("attacker")
    n = int(len(has))
    dropped = has & (cols.get("attacker", "dropped")[:n] != 0)
    return {"samples": np.flatnonzero(dropped).tolist(), "T": float(rsc.T), "n_samples": n, "source": p}
