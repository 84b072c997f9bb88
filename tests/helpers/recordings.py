"""Recordings in a test: the columnar reader's columns against the reference reader's messages."""

from __future__ import annotations

import dataclasses

import numpy as np

from testbed.wire import messages as msg


def assert_columns_equal_reference(cols, rec):
    """Every field of every telemetry dataclass the reference reader decoded equals the column's value."""
    names = {"plant": msg.PlantTelemetry, "encoder": msg.EncoderTelemetry, "controller": msg.ControllerTelemetry,
             "attacker": msg.AttackerTelemetry}
    for role, cls in names.items():
        ref = rec.telemetry[role]
        has = cols.has(role)
        assert sorted(ref) == np.flatnonzero(has).tolist(), role
        for f in dataclasses.fields(cls):
            if f.name == "k":
                continue
            col = cols.get(role, f.name)
            for k, t in ref.items():
                want = getattr(t, f.name)
                if role == "encoder" and t.silent and f.name in ("xi", "q", "E", "symbol"):
                    continue  # not sent; the columns hold NaN / -1 there
                if f.name == "x_meas" and want == ():  # no sensor model: not sent; the column holds NaN
                    assert np.isnan(col[k]).all(), (role, f.name, k)
                elif isinstance(want, tuple):
                    assert np.array_equal(col[k], np.array(want)), (role, f.name, k)
                else:
                    assert col[k] == want, (role, f.name, k)
        for (r, name), c in cols.lay.cols.items():  # the rows the role did not record: the absent value
            if r == role and (~has).any():
                gone = np.asarray(cols.get(role, name))[~has]
                assert (np.isnan(gone).all() if np.isnan(c.absent) else (gone == c.absent).all()), (role, name)
    if rec.plant_final is not None:
        assert cols.final["k"] == rec.plant_final.k and np.array_equal(cols.final["x"], rec.plant_final.x)
    assert len(cols.events) == len(rec.events) and len(cols.status) == len(rec.status)
    assert dict(cols.counts) == dict(rec.counts)
