"""A chunk of a campaign's simulated runs on the batch kernel: the runs that share a loop (everything
but the initial state and the attack) in one ``simulate_batch`` call.

The batch kernel equals the per-sample simulator bit for bit (x_k, E_k, theta_k, saturations, the
final loop state of both ends: ``tests/sim/test_simulate.py``, ``tests/core/test_methods.py``), and the escape
is judged by the same ``judge_escape`` from the same final loop state, so a row from here equals
``testbed simulate --json`` of its scenario (``tests/runs/test_campaign.py`` checks every row of a campaign
against the per-sample simulator).  A run the kernel cannot run -- an FMU plant, a plant that is a
device ([plant.sensor], ...), a user's method,
physical timing, an online (greedy) attacker, a ``[network]`` channel -- or whose flow diverged in the kernel (the per-sample
simulator then says where and why) runs on the per-sample simulator.
"""

from __future__ import annotations

import json
import tomllib
from typing import TYPE_CHECKING

import numpy as np

from ..loop.channel import LOSS_KINDS
from ..sim.trajectory import kernel_refusal

if TYPE_CHECKING:
    from ..scenario import Scenario


def batch_key(sc: Scenario, text: str, base_dir: str) -> str | None:
    """What a run shares with the runs it can share a kernel call with; None: the per-sample simulator."""
    if kernel_refusal(sc) is not None:
        return None  # the kernel cannot run it (the one predicate of testbed simulate's kernel)
    if sc.run.timing != "ideal" or sc.attack.online or sc.network is not None:
        return None  # the kernel runs these one at a time with their latencies, attacker or channel (testbed simulate)
    data = tomllib.loads(text)
    data.get("plant", {}).pop("x0", None)
    data.pop("attack", None)
    data.pop("name", None)
    data.pop("description", None)
    return json.dumps(data, sort_keys=True) + "\0" + base_dir


def run_group(scs: list) -> list[dict | None]:
    """The outcome of each scenario of one group (one ``batch_key``) from one kernel call; None for a run
    whose flow diverged (the per-sample simulator runs it)."""
    from ..sim.batch import FLOW_OK, EscapeCriterion, json_clean, judge_escape, run_outcome, simulate_batch
    from .engine import settle_samples

    sc0 = scs[0]
    N = sc0.n_steps
    model = sc0.make_model()
    plant = sc0.make_plant()
    method = sc0.make_method()
    X0 = np.array([sc.x0 for sc in scs], dtype=np.float64)
    tab = np.zeros((len(scs), N), dtype=np.uint8)
    for j, sc in enumerate(scs):
        th = sc.theta(N)
        if th is not None:
            tab[j, :len(th)] = np.asarray(th, dtype=np.uint8)[:N]
    b = simulate_batch(plant, sc0.K, sc0.quantizer, X0, N, model=model, theta=tab, sched_idx=np.arange(len(scs)),
                       u_max=sc0.controller.u_max, flow=sc0.flow, record=True, method=method, specialize=True)
    tol = sc0.run.converge_tol
    crit = EscapeCriterion.for_loop(model, sc0.quantizer, tol)
    assert b.x is not None and b.theta is not None and b.state_final is not None  # record=True
    ok = np.flatnonzero(b.status == FLOW_OK)
    esc = np.zeros(len(scs), dtype=bool)
    if ok.size:
        kw = {} if sc0.method.name == "paper" else {"method": method}
        esc[ok] = judge_escape(plant, sc0.K, sc0.quantizer, b.x_final[ok], b.state_final[ok],
                               np.full(ok.size, FLOW_OK), crit, model=model, flow=sc0.flow, **kw)
    bits = method.codebook(model.n, sc0.quantizer).bits
    out: list[dict | None] = []
    for j, sc in enumerate(scs):
        if b.status[j] != FLOW_OK or b.mismatch[j] != 0:
            out.append(None)
            continue
        lost = int(b.theta[j].sum())
        out.append(json_clean({
            # testbed simulate --json's outcome of the same run (one function), from the kernel's arrays
            **run_outcome(sc, b.x[j], b.x_final[j], b.theta[j], bits=bits, saturations=int(b.saturations[j]),
                          agree=True, diverged=False, escaped=esc[j],
                          # no channel, ideal timing, every ack delivered: each lost sample is the attacker's
                          losses={**dict.fromkeys(LOSS_KINDS, 0), "attacker": lost}),
            "settle_samples": settle_samples(b.x[j], b.x_final[j], tol)}))
    return out
