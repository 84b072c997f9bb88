"""The in-process simulators: the same loop as a live run, without processes or a network.

* ``loop``: ``simulate_loop``, one trajectory sample by sample with the live nodes' own protocol
  objects (``testbed.loop.protocol``), every per-sample quantity in a ``SimResult``;
* ``kernel``: ``_batch_kernel``, the one compiled loop (numba), and ``kernelcache``: that kernel
  specialized per plant and cached on disk;
* ``batch``: ``simulate_batch``, many initial states and schedules at once on the kernel (what the
  analysis runs), the escape criterion, and a run's JSON summary (``summarize``);
* ``trajectory``: ``simulate_scenario``, a scenario on the kernel where it can run (every
  per-sample array, bit for bit the loop's), else on the loop.
"""
