"""The summary of a recording: ``build_summary`` and the sections ``testbed.Run.summary`` documents.

``testbed.open`` builds its ``Run`` from it, and ``testbed report`` is that ``Run`` plus the
report's own sections (resimulation, telemetry check, recording details, actuation).  Added
here beside the keys of ``build_summary`` (those of ``testbed simulate --json`` and the live ones):

* ``live``, ``source``: where the run came from (a simulation has nominal times only: ``timing`` None);
* ``dos``: the attack intervals -- an ``intervals`` attack's as declared (``priced`` says so), else
  the runs of lost samples the attacker logged (its per-sample ``attack_on``, one attack per run;
  ``logged_intervals`` always) --, their lengths, the realized rates N(H)/H and |A(H)|/H, and the
  smallest kappa_F, kappa_D at the scenario's rho_F, rho_D (``attackers.budget.check``), checked
  against the scenario's declared budget when it has one;
* ``dropped_by_attacker``: the samples the attacker's log says it dropped;
* ``agreement``: encoder and decoder xi_k, E_k compared at every sample;
* ``outcome``: the launcher's verdict (``"simulated"`` for a simulation's recording).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .summary import build_summary

if TYPE_CHECKING:
    from ..scenario import Scenario
    from .columns import Columns


def recorded_attack(cols: Columns, N: int) -> tuple[np.ndarray, np.ndarray]:
    """Per sample, from the attacker's own log: a DoS interval was on (``attack_on``), it dropped the
    symbol (``dropped``); False where the attacker recorded nothing."""
    A = cols.has("attacker")[:N]
    return A & (cols.get("attacker", "attack_on")[:N] != 0), A & (cols.get("attacker", "dropped")[:N] != 0)


def dos_section(sc: Scenario, attack_on: np.ndarray, horizon: float) -> dict:
    """The ``dos`` section (module docstring) of a run of ``horizon`` seconds with the attacker's log ``attack_on``."""
    from attackers.budget import check, realized_rates
    from attackers.schedule import Schedule

    logged = Schedule.from_theta(attack_on.astype(np.uint8), sc.T) if attack_on.size else Schedule.empty()
    if sc.attack.kind == "intervals":
        # priced as declared: back-to-back attacks lose the samples one longer attack would lose,
        # for less duration, so the log's runs of lost samples would overprice them
        full = sc.attack.schedule(sc.T, horizon)
        assert full is not None  # an offline kind
        sch = Schedule.from_list([iv for iv in full.intervals if iv[0] < horizon - 1e-9]) if horizon > 0 else full
        priced = "declared intervals"
    else:
        sch, priced = logged, "runs of lost samples in the attacker's log (one attack each)"
    out: dict = {"intervals": [list(iv) for iv in sch.intervals], "count": len(sch),
                 "lengths": [float(x) for x in sch.lengths], "total_duration": float(sch.total_duration),
                 "horizon": horizon, "priced": priced, "logged_intervals": [list(iv) for iv in logged.intervals]}
    if horizon > 0:
        rr = realized_rates(sch, horizon)
        out["realized"] = {"frequency": rr[0], "duration_fraction": rr[1]}
    declared = sc.attack.budget
    if declared is not None:
        kF, rF, kD, rD = declared
        rep = check(sch, rF, rD, horizon=horizon if horizon > 0 else None)
        out["budget"] = {"declared": {"kappa_F": kF, "rho_F": rF, "kappa_D": kD, "rho_D": rD},
                         "kappa_F_min": rep.kappa_F_min, "kappa_D_min": rep.kappa_D_min,
                         "within": bool(rep.satisfies(kF, kD))}
    else:
        out["budget"] = None
    return out


def agreement(cols: Columns, N: int) -> dict:
    """Encoder and decoder (xi_k, E_k) compared bit for bit at every sample both recorded."""
    e_ok = cols.has("encoder")[:N] & (cols.get("encoder", "silent")[:N] == 0)
    both = e_ok & cols.has("controller")[:N]
    xi_e, xi_c = cols.get("encoder", "xi")[:N], cols.get("controller", "xi")[:N]
    E_e, E_c = cols.get("encoder", "E")[:N], cols.get("controller", "E")[:N]
    differ = np.flatnonzero(both & ((E_e != E_c) | np.any(xi_e != xi_c, axis=1)))
    missing = np.flatnonzero(~both)
    compared = int(np.count_nonzero(both))
    return {"samples": N, "compared": compared, "disagree": int(differ.size), "disagree_at": differ[:50].tolist(),
            "not_compared": int(missing.size), "not_compared_at": missing[:50].tolist(),
            "all_agree": not differ.size and not missing.size}


#: the keys ``recording_summary`` adds to ``build_summary``'s, in this order
SECTIONS = ("live", "source", "dos", "dropped_by_attacker", "agreement", "outcome")


def recording_summary(cols: Columns, sc: Scenario) -> dict:
    """``build_summary`` of a recording's columns (per-sample values as numpy arrays) and the sections above."""
    runmeta = cols.metadata.get("testbed.run", {})
    launcher = cols.summaries.get("launcher", {})
    plant = sc.make_model()
    cb = sc.make_method().codebook(plant.n, sc.quantizer)
    start = cols.start
    run_id = start.run_id if start else runmeta.get("run_id", "?")
    ack_via = runmeta.get("ack_via_attacker", "false") == "true" or bool(start and start.ack_via_attacker)
    out = build_summary(sc, cols, run_id=run_id, ack_via_attacker=ack_via,
                        nodes=launcher.get("nodes") or {}, faults=launcher.get("faults") or [], codebook=cb,
                        arrays=True)
    live = cols.source == "live"
    out["live"] = live
    out["source"] = cols.source
    N = out["samples"]
    if not live:
        out["timing"] = None  # a simulation has nominal times only
    attack_on, dropped = recorded_attack(cols, N)
    out["dos"] = dos_section(sc, attack_on, N * sc.T)
    out["dos"]["attacker_log_samples"] = int(np.count_nonzero(cols.has("attacker")))
    out["dos"]["counts"] = "the attacker's losses only (losses.attacker), not the channel's, late or withheld ones"
    out["dropped_by_attacker"] = int(dropped.sum())
    out["agreement"] = agreement(cols, N)
    out["outcome"] = launcher.get("outcome", "simulated" if not live else None)
    return out
