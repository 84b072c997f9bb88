"""``testbed export RUN.mcap -o PATH``: a run as Parquet or CSV, one row per sample.

Its arguments and text output; the table itself is ``testbed.runs.export``.
"""

from __future__ import annotations

import argparse
import json
import sys

from ..common import cliargs
from ..runs.export import FORMATS, export


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", help="an MCAP file written by testbed run or testbed simulate --out")
    p.add_argument("--format", choices=FORMATS, default=None,
                   help="parquet or csv (default: from the output's suffix, else parquet)")
    p.add_argument("-o", "--output", metavar="PATH", required=True, help="the file to write")
    cliargs.add_json(p, "what was written (path, format, rows, columns)")
    cliargs.add_trust_code(p)


def main(args: argparse.Namespace) -> int:
    from ..runs.run import column_names
    from ..runs.run import open as open_run

    fmt = args.format or ("csv" if str(args.output).lower().endswith(".csv") else "parquet")
    run = open_run(args.recording, trust_code=args.trust_code)
    out = export(run, args.output, fmt)
    cols = column_names(run.arrays)  # the names only: run.columns() would copy every vector's columns
    if args.json:
        print(json.dumps({"path": str(out), "format": fmt, "rows": run.N, "columns": cols}))
    else:
        print(f"{out}: {run.N} rows x {len(cols)} columns ({fmt})", file=sys.stderr)
    return 0
