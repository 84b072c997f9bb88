"""Simulations in a test: the paper's loop as scenario text, a simulation recorded to MCAP, and the checks
that the per-sample loop and the batch kernel give one result, bit for bit."""

from __future__ import annotations

import json

import numpy as np


def paper_loop_toml(x0=(0.1, 0.1), E0=0.1, mode: str | None = None) -> str:
    """The ``[plant]``, ``[quantizer]`` and ``[controller]`` tables of the paper's example (the Lienard plant
    a = 1/3, b = 0.02; T = 0.1, M = 6, L = 10; the paper's K) as scenario text, for a test's own scenario;
    ``x0``, ``E0`` and the quantizer's ``mode`` (none: the default) as given."""
    return (f'[plant]\nname = "lienard"\nparams = {{ a = 0.3333333333333333, b = 0.02 }}\nx0 = [{x0[0]}, {x0[1]}]\n\n'
            f"[quantizer]\nT = 0.1\nM = 6\nL = 10.0\nE0 = {E0}\n" + (f'mode = "{mode}"\n' if mode else "")
            + "\n[controller]\nK = [[-1.81, -1.90]]\n")


def sim_recording(tmp_path, name="paper", **over):
    """A simulation of scenario ``name`` (with ``over``) recorded to ``tmp_path/NAME.mcap``: (sc, res, path)."""
    from testbed import scenario
    from testbed.record import recording
    from testbed.sim.batch import simulate_scenario

    sc = scenario.with_overrides(scenario.load(name), over)
    res = simulate_scenario(sc)
    path = tmp_path / f"{name}.mcap"
    recording.record_simulation(path, sc, res, overrides=over)
    return sc, res, path


#: the per-sample arrays of a ``SimResult`` that the batch kernel and the per-sample loop must agree on
SIM_ARRAYS = ("t", "x", "u", "q", "q_enc", "xi_enc", "E_enc", "xi_dec", "E_dec", "theta", "symbols", "saturated",
              "x_final", "reason", "withheld", "delays", "u_missing", "loop_state")


def same_bits(a, b) -> bool:
    """Bit for bit (NaN where NaN, -0.0 where -0.0), dtype and shape too."""
    if a is None or b is None:
        return a is None and b is None
    a, b = np.asarray(a), np.asarray(b)
    if a.dtype != b.dtype or a.shape != b.shape:
        return False
    return a.tobytes() == b.tobytes()


def both_simulators(sc, **kw):
    """``simulate_scenario`` of ``sc`` on the per-sample loop and on the batch kernel: (per, batch)."""
    from testbed.sim.trajectory import simulate_scenario

    per = simulate_scenario(sc, simulator="per-sample", **kw)
    bat = simulate_scenario(sc, simulator="batch", **kw)
    assert per.simulator == "per-sample" and bat.simulator == "batch"
    return per, bat


def assert_simulators_identical(sc, per, bat):
    """The two simulators' results of ``sc`` are one: every array bit for bit, the scalars, the gain, the
    counters and the JSON summary (but its ``simulator``)."""
    from testbed.sim.batch import summarize

    for name in SIM_ARRAYS:
        assert same_bits(getattr(per, name), getattr(bat, name)), name
    for name in ("T", "flow_status", "diverged_at", "plant_fault", "plant_fault_at", "method_fault",
                 "lockstep_breaks"):
        assert getattr(per, name) == getattr(bat, name), name
    assert np.array_equal(per.K, bat.K)
    assert per.counters == bat.counters
    sp, sb = summarize(sc, per), summarize(sc, bat)
    assert sp.pop("simulator") == "per-sample" and sb.pop("simulator") == "batch"
    assert json.dumps(sp) == json.dumps(sb)
