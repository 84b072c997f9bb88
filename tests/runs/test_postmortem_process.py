"""Post-mortems as their own processes (process tier): what ``testbed report``, ``export``, ``compare`` and
``resimulate`` write is whole when the process ends, although they end without the interpreter's teardown
(``testbed.cli.FAST_EXIT_AFTER_HANDLERS``: the exit handlers run, then the process exits at once)."""

from __future__ import annotations

import json

import pytest
from helpers.cli import tb
from helpers.sims import sim_recording

from testbed.record.summary import to_lists
from testbed.runs.report import report

pytestmark = pytest.mark.process


def test_the_post_mortems_output_is_whole_when_their_process_ends(tmp_path):
    sc, _, path = sim_recording(tmp_path, "paper", duration=30.0)
    rc, out, err = tb("report", path, "--json")
    assert rc == 0, err
    assert json.loads(out) == json.loads(json.dumps(to_lists(report(path))))  # every key, every sample
    pq = tmp_path / "run.parquet"
    rc, out, err = tb("export", path, "--format", "parquet", "-o", pq)
    assert rc == 0, err
    import pyarrow.parquet as pqlib

    t = pqlib.read_table(pq)
    assert t.num_rows == sc.n_steps and t.column("k").to_pylist() == list(range(sc.n_steps))
    rc, out, err = tb("compare", path, path, "--json")
    assert rc == 0 and json.loads(out)["identical"] is True, (out, err)
    rc, out, err = tb("resimulate", path, "--json")
    assert rc == 0 and json.loads(out)["reproduced"] is True, (out, err)
    # a figure written beside the JSON: whole too
    rc, out, err = tb("report", path, "--json", "--plot", tmp_path / "fig.png")
    assert rc == 0 and (tmp_path / "fig.png").stat().st_size > 1000, err
