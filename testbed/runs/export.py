"""``testbed export RUN.mcap --format parquet|csv -o PATH``: one row per sample, for any data tool.

Its arguments and text output are ``testbed.commands.export``; this module is what it computes.

The columns are those of ``testbed.open(RUN).columns()`` (``testbed.runs.run``):
``k``, ``t``, ``x1..xn``, ``u1..um``, ``q1..qn``, ``xi1..xin``, ``E``, ``E_dec``,
``xi_dec1..``, ``q_enc1..``, ``theta``, ``symbols``, ``saturated``,
``attack_on``, ``dropped``, and for live runs the timing columns (seconds).
Parquet files carry the run's metadata in their schema metadata: every
metadata record of the recording (``testbed.scenario`` with the scenario's
TOML, ``testbed.run``, ``testbed.software``, ...) as a JSON object under its
name, and ``testbed.summary`` (the report's scalar results).  CSV has the
columns only.  Parquet is written by ``testbed.common.parquet`` (plain pages, zstd, statistics),
CSV by pyarrow.

Exit codes: 0 written, 2 unreadable recording or unwritable output.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..common.errors import BadInput
from .run import flat_columns

if TYPE_CHECKING:
    from .run import Run

FORMATS = ("parquet", "csv")


#: rows of a run converted and written at a time (``export``), one Parquet row group each: the export's memory is
#: that of the run's arrays and one group's pages, not a copy of the run
ROWS = 1 << 16


def _metadata_text(run: Run) -> dict[str, str]:
    meta = {name: json.dumps(rec) for name, rec in run.metadata.items()}
    meta["testbed.summary"] = json.dumps(_scalars(run.summary), default=str)
    meta["testbed.source"] = run.source
    return meta


def _metadata(run: Run) -> dict[bytes, bytes]:
    return {k.encode(): v.encode() for k, v in _metadata_text(run).items()}


def table(run: Run, rows: slice | None = None, metadata: dict[bytes, bytes] | None = None) -> Any:
    """The run as a ``pyarrow.Table`` with the metadata described above (``rows``: those rows only;
    ``metadata``: ``_metadata(run)`` when the caller has it already)."""
    import pyarrow as pa

    from ..record.summary import arrow_array, arrow_plain

    arrays = run.arrays if rows is None else {k: v[rows] for k, v in run.arrays.items()}
    cols = flat_columns(arrays)
    # over the numpy buffers: ``pa.table`` of numpy arrays would import pandas (40 MB, a few tenths of a second)
    return pa.Table.from_arrays([arrow_array(a) if arrow_plain(a) else pa.array(a) for a in cols.values()],
                                names=list(cols), metadata=_metadata(run) if metadata is None else metadata)


def _scalars(d: dict) -> dict:
    """The JSON-able, non-per-sample part of a summary."""
    from ..record.summary import to_lists

    return {k: v for k, v in to_lists(d).items() if not (isinstance(v, list) and len(v) > 64)}


def export(run: Run, path: str | Path, fmt: str) -> Path:
    """Write ``run`` (a ``testbed.runs.run.Run``) to ``path`` as Parquet or CSV."""
    path = Path(path)
    if fmt not in FORMATS:
        raise BadInput(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    # streamed: ROWS rows at a time, so that no second copy of the run is made (one Parquet row group each)
    try:
        if fmt == "parquet":
            _parquet(run, path)
        else:
            import pyarrow.csv as pcsv

            meta = _metadata(run)
            first = table(run, slice(0, ROWS), meta)
            with pcsv.CSVWriter(path, first.schema) as writer:
                writer.write_table(first)
                for a in range(ROWS, run.N, ROWS):
                    writer.write_table(table(run, slice(a, a + ROWS), meta))
    except OSError as e:
        raise BadInput(f"cannot write {path}: {e}") from None
    return path


def _parquet(run: Run, path: Path) -> None:
    """The run as Parquet, by ``testbed.common.parquet`` (plain pages, zstd): the table ``table(run)`` is, read back
    by pyarrow, polars or pandas, without pyarrow's imports and write buffers beside the run's columns."""
    from ..common.parquet import ParquetWriter

    first = flat_columns({k: v[:0] for k, v in run.arrays.items()})
    with ParquetWriter(path, list(first), [a.dtype for a in first.values()], _metadata_text(run)) as writer:
        for a in range(0, run.N, ROWS):
            writer.write(flat_columns({k: v[a:a + ROWS] for k, v in run.arrays.items()}))


__all__ = ["export", "table", "FORMATS"]
