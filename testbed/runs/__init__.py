"""Whole runs: one type, the ``Run``, for recordings and simulations alike, and what is built on it.

* ``run``: ``Run``, ``open`` (a recording), ``simulate`` (a scenario): ``testbed.open``,
  ``testbed.simulate``, ``testbed.Run``;
* ``report``: ``testbed report``, a ``Run`` and the report's own sections;
* ``compare``: ``testbed compare`` and ``testbed.compare``, two runs sample by sample;
* ``resimulate``: ``testbed resimulate``, a recording re-run in the simulator, sample by sample;
* ``export``: ``testbed export``, a run as Parquet or CSV.
"""
