"""Campaigns and the run engine: many runs of one scenario, one row each (``testbed campaign``,
``testbed versus``; docs/campaigns.md).

- ``engine``: a point (scenario x method x attack seed) -> its row; the Wilson interval and the
  paired difference of ``testbed versus``;
- ``spec``: the campaign file, its runs (the product of the axes) and their seeds;
- ``batch``: a chunk of simulated runs that share a loop, on the batch kernel;
- ``run``: running a campaign (resumable, local workers or a Dask cluster), ``--verify``, its figure.
"""
