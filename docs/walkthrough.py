"""A notebook-style walkthrough of the Python API (docs/api.md); ``tests/runs/test_postmortem.py`` runs it.

    python docs/walkthrough.py [WORKDIR]

Each ``# %%`` cell runs as it is in a Jupyter or VS Code notebook. It uses only the public API:
``testbed.simulate``, ``testbed.open``, ``testbed.compare``, ``testbed.BadInput`` and the ``Run``.
"""

# %% 1. Simulate the paper's example, record it and draw it (as `testbed simulate paper --out --plot` do)
import sys
import tempfile
from pathlib import Path

import numpy as np

import testbed

work = Path(sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp(prefix="walkthrough-"))
sim = testbed.simulate("paper", duration=10)
print(sim)                                     # Run(simulate: scenario paper, 100 samples of T = 0.1 s, ...)
path = sim.save(work / "paper.mcap")           # the recording `testbed simulate paper --duration 10 --out` writes
sim.plot(work / "paper.pdf", size="column")    # the figure of `--plot`: .png, .pdf or .svg; one IEEE column

# %% 2. Open the recording: one numpy array per quantity, one entry per sample k
run = testbed.open(path)
a = run.arrays
print(sorted(a))                               # E, E_dec, attack_on, dropped, k, q, q_enc, saturated, ...
print(a["x"].shape, a["E"][:3], int(a["theta"].sum()), "samples lost")
assert np.array_equal(a["E"], sim.arrays["E"])  # the recording holds exactly what the simulator computed

# %% 3. Where were the DoS intervals, and how fast did E_k shrink?
lost = np.flatnonzero(a["theta"])
print("lost samples", lost.min(), "..", lost.max(), "; intervals", run.summary["dos_intervals"])
rate = np.diff(np.log10(a["E"][a["E"] > 0]))
print(f"log10 E_k per sample: median {np.median(rate):.3f}, worst {rate.max():.3f}")

# %% 4. The same run as a table (pandas / polars, when installed)
try:
    df = run.to_pandas()
    print(df[["k", "t", "x1", "x2", "E", "theta"]].head())
except ImportError as e:
    print(e)

# %% 5. What if x0 were further out and the quantizer coarser? Overrides are validated like the file
far = testbed.simulate("paper", x0=[0.1, -0.1], M=8, duration=10, attack={"intervals": [[2.0, 1.5]]})
print(far.summary["converged"], far.summary["final_norm"], far.summary["dos_intervals"])
try:
    testbed.simulate("paper", x0=[0.5, 0.5])   # outside the quantizer's first box: the message says what to pass
except testbed.BadInput as e:
    print("BadInput:", e)

# %% 6. Compare two runs sample by sample (as `testbed compare A B --json` does)
c = testbed.compare(run, sim)
print(c["identical"], c["first_divergence"])   # True None: the recording is the simulation
c = testbed.compare(run, far)
print(c["identical"], c["first_divergence"], f"max ||x_A - x_B|| = {c['max_state_error']:.3g}")
assert c["first_divergence"] == 0              # x0 differs
