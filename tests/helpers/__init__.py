"""What the tests share, one module a concern (a test module never imports another: ``tests/repo/test_layers.py``).

* ``helpers.cli``: the ``testbed`` command in its own process (``tb``, ``tb_run``, ``run_cli``, ``tb_cmd``) or
  in this one (``tb_here``, ``tb_run_here``), and the options every command shares (``SHARED``);
* ``helpers.procs``: the processes of a run (``procs_with``, ``cmdlines``, ``reap``);
* ``helpers.live``: live runs (``live``, ``live_exact`` under the one rerun policy), the keys a live run must
  reproduce bit for bit and its topologies, the simulator's reference, ``mismatch``, ``JoinAnnounce``;
* ``helpers.sims``: the paper's loop as scenario text, a simulation recorded, the per-sample loop against
  the batch kernel bit for bit;
* ``helpers.recordings``: the columnar reader against the reference reader;
* ``helpers.verdicts``: the verdicts of the live tests that ``tests/repo/test_failclosed.py`` also runs on
  broken builds;
* ``helpers.faulty_method``: a user's method that faults on purpose (source text).

The fixtures are in ``tests/conftest.py``; the rerun policy and the capabilities in ``tests/failclosed.py``.
"""
