"""``testbed report RUN.mcap [--json] [--plot PATH.png]``: the post-mortem of a recording.

Its arguments and text output are ``testbed.commands.report``; this module is what it computes.

Everything comes from the recording alone: the scenario is rebuilt from the
TOML stored in its metadata (with the run's overrides), the per-sample arrays
from the telemetry topics.  The report starts from the recording's ``testbed.Run``
(``testbed.runs.run.run_of_recording``, what ``testbed.open`` returns): its summary goes
through the same ``testbed.record.summary.build_summary`` as ``testbed run`` (and,
inside it, ``testbed.sim.batch.summarize``), so every key of ``testbed simulate --json``
means the same thing here, and ``testbed.record.sections`` adds ``dos``, ``agreement``,
``dropped_by_attacker`` and ``outcome``.  The report adds:

* ``losses_as_dos``: every lost sample taken as if it were DoS, against Theorem 1's region;
* ``saturation_events``, ``recording`` (source,
  truncation, message counts, software versions);
* ``actuation`` (physical timing): the delays the plant measured, the bounds and
  margins the quantizer used;
* ``resimulation``: the recording re-run through the simulator (``testbed resimulate``);
* ``telemetry_check``: each node's own account of its telemetry (records and digest,
  in its summary) against what the recording holds;
* ``plant_source``: how the plant module was loaded, ``{"ref", "sha256",
  "loaded_from": "import" | "recording", "differs", ...}`` (None for recordings
  that store no plant module), and ``model_source`` the same for a ``[model]`` of
  another class.

Exit codes: 0 report written, 2 unreadable file or no scenario in it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from ..record.faults import Fault
from ..record.summary import load, to_lists
from ..wire import messages as msg
from ..wire import transport
from .resimulate import resimulation
from .run import run_of_recording

if TYPE_CHECKING:

    from ..record.columns import Columns
    from ..scenario import Scenario
    from ..scenario.spec import DelaySpec
    from .run import Run


def losses_as_dos(sc: Scenario, theta: np.ndarray) -> dict:
    """Every lost sample -- the attacker's, the channel's, late and withheld -- taken together as if it
    were DoS: the runs of lost samples as attacks (one each), their realized average frequency N(H)/H and
    duration fraction |A(H)|/H (``attackers.budget.realized_rates``), the smallest kappa_F, kappa_D at
    those rates (Assumptions 3 and 4, ``attackers.budget.check``), and whether the point lies in Theorem 1's
    allowable region (``analysis.allowable_region``, the paper's rule) of the scenario's model, taken as
    rates rho_F, rho_D with no intercepts (``theorem1.in_allowable_region``).  Theorem 1 asks it of the
    long-run rates of a budget whose intercepts kappa_F, kappa_D absorb a finite run's excess:
    ``theorem1.budget`` is the scenario's budget (``analysis.summary.scenario_budget``) in the same
    region, the verdict ``testbed analyze`` prints.  The two differ when a short run's losses are
    all initial energy (an ``intervals`` attack: rho_F = rho_D = 0 with the smallest kappas)."""
    from attackers.budget import check, realized_rates
    from attackers.schedule import Schedule

    H = len(theta) * sc.T
    sch = Schedule.from_theta(np.asarray(theta, dtype=np.uint8), sc.T) if len(theta) else Schedule.empty()
    out: dict = {"what": "all losses as if DoS: runs of lost samples, one attack each", "count": len(sch),
                 "total_duration": float(sch.total_duration), "horizon": H}
    if H <= 0:
        return out
    fF, fD = realized_rates(sch, H)
    out.update(frequency=fF, duration_fraction=fD)
    if fD < 1:
        rep = check(sch, fF, fD, horizon=H)
        out.update(kappa_F_min=rep.kappa_F_min, kappa_D_min=rep.kappa_D_min)
    try:
        from ..analysis import Loop, allowable_region
        from ..analysis.summary import scenario_budget

        reg = allowable_region(Loop.from_scenario(sc), "paper")
        (kF, rF, kD, rD), src = scenario_budget(sc)
        out["theorem1"] = {"rule": "paper", "rho_F_max": reg.rho_F_max, "rho_D_max": reg.rho_D_max,
                           "checks": "the realized rates over the horizon taken as rho_F, rho_D (no intercepts)",
                           "in_allowable_region": bool(fD < 1 and reg.holds(fF, fD)),
                           "budget": {"kappa_F": kF, "rho_F": rF, "kappa_D": kD, "rho_D": rD, "source": src,
                                      "checks": "the declared budget's rates rho_F, rho_D, with its intercepts "
                                                "kappa_F, kappa_D (what testbed analyze checks)",
                                      "in_allowable_region": bool(rD < 1 and reg.holds(rF, rD))}}
    except Exception as e:  # noqa: BLE001 - the region needs the model's Jacobians; say why it is missing
        out["theorem1"] = {"rule": "paper", "in_allowable_region": None, "why": f"{type(e).__name__}: {e}"}
    return out


def _actuation_section(sc: Scenario, cols: Columns, N: int) -> dict | None:
    """Physical timing: the delays the plant measured and the bounds and margins the quantizer used."""
    if sc.run.timing != "physical":
        return None
    from ..record.summary import late_for_schedule, percentiles

    have = cols.has("plant")[:N]
    theta = cols.get("plant", "theta")[:N]
    delay = cols.get("plant", "delay_ns")[:N]
    rx, t = cols.get("plant", "u_rx_ns")[:N], cols.get("plant", "t_ns")[:N]
    recv = have & (theta == 0)
    arrived = recv & (rx != msg.NO_TIME) & (t != msg.NO_TIME)
    arrival = rx[arrived] - t[arrived]
    tp = sc.timing_params
    qp = sc.quantizer

    def bound(d: DelaySpec | None) -> dict | None:
        return None if d is None else {"nominal": d.nominal, "min": d.min, "max": d.max, "declared": d.declared}

    return {"actuation": sc.run.actuation, "rule": qp.rule, "scheduled_delay_s": int(tp[2]) / 1e9,
            "deadline_s": int(tp[3]) / 1e9, "loss_deadline_s": int(tp[4]) / 1e9,
            "bound": bound(sc.run.delay), "bound_lost": bound(sc.run.delay_lost),
            "delay_hat": qp.delay_hat, "margin_gain": qp.margin_gain, "delay_hat_lost": qp.delay_hat_lost,
            "margin_gain_lost": qp.margin_gain_lost, "L_u": sc.L_u,
            "delay_us": {"received": percentiles(delay[recv]), "lost": percentiles(delay[have & (theta == 1)])},
            "arrival_us": percentiles(arrival),
            "late_for_schedule": late_for_schedule(sc, arrival)}


def telemetry_check(cols: Columns, N: int) -> list[dict]:
    """Each node's own account of its telemetry (the count of records in its summary) against the
    records the recording holds: a difference means records were lost, forged or altered on the way
    (the launcher compares digests too; a recording keeps the decoded fields, not the bytes)."""
    out = []
    for role in transport.ROLES:
        s = cols.summaries.get(role) or {}
        if "telemetry_records" not in s:
            continue
        held = int(np.count_nonzero(cols.has(role)[:N])) + (1 if role == "plant" and cols.final is not None else 0)
        if held != s["telemetry_records"] or cols.rejected.get(role):
            out.append(Fault(role=role, kind="telemetry_mismatch",
                             detail=f"the recording holds {held} records, the node published {s['telemetry_records']}"
                                    + (f"; {cols.rejected[role]} rejected (k outside [0, N))"
                                       if cols.rejected.get(role) else "")).to_dict())
    return out


def _security(runmeta: dict) -> dict | None:
    """How the recorded run's sessions were secured (``None`` for a simulation or an older recording)."""
    v = runmeta.get("security")
    try:
        return json.loads(v) if v else None
    except ValueError:
        return None


#: how many samples ``testbed report`` resimulates by default (about 1.3 s; every sample of a
#: run up to 1,000 s at T = 0.1 s or 10 s at 1 kHz): ``--resimulate all`` or ``testbed resimulate`` for more
RESIMULATE_SAMPLES = 10_000


def report(path: str | Path | tuple[Columns, Scenario], *, arrays: bool = False,
           resimulate: int | None | Literal["default"] = "default", trust_code: bool = False) -> dict:
    """The report of one recording (a path, or ``(columns, scenario)`` from ``load``), as a JSON-able dict.

    ``arrays``: the per-sample values stay numpy arrays (``record.summary.write_json`` streams them).
    ``resimulate``: the resimulation check covers samples 0 .. resimulate - 1 (None: all, 0: none;
    "default": ``RESIMULATE_SAMPLES``, read when the report is made).  ``trust_code``: ``--trust-code``
    (``testbed.runs.run.open``).
    """
    out = report_of_run(run_of(path, trust_code=trust_code), resimulate=resimulate)
    return out if arrays else to_lists(out)


def run_of(path: str | Path | tuple[Columns, Scenario], *, trust_code: bool = False) -> Run:
    """The ``testbed.Run`` of a recording (a path, or ``(columns, scenario)`` from ``load``), read with the
    fields the report needs (``record.summary.load``; ``trust_code`` as in ``testbed.runs.run.open``)."""
    cols, sc = load(path, trust_code=trust_code) if isinstance(path, (str, Path)) else path
    return run_of_recording(cols, sc)


def report_of_run(run: Run, *, resimulate: int | None | Literal["default"] = "default") -> dict:
    """The report of a recording's ``Run`` (``testbed.runs.run.run_of_recording``): its whole summary and the
    report's own sections (module docstring); per-sample values as numpy arrays."""
    if resimulate == "default":
        resimulate = RESIMULATE_SAMPLES
    cols, sc, s = run.recorded_columns, run.scenario, run.recorded_summary
    assert cols is not None and s is not None  # a recording's Run (run_of_recording)
    path = cols.path
    runmeta = cols.metadata.get("testbed.run", {})
    start = cols.start
    N = run.N
    out = {k: v for k, v in s.items() if k not in ("dos", "dropped_by_attacker", "agreement", "outcome")}
    out["dos"] = s["dos"]
    out["losses_as_dos"] = losses_as_dos(sc, run.arrays["theta"])
    out["dropped_by_attacker"] = s["dropped_by_attacker"]
    out["agreement"] = s["agreement"]
    out["saturation_events"] = [e["k"] for e in run.events if e["kind"] == "saturation"]
    out["outcome"] = s["outcome"]
    out["actuation"] = _actuation_section(sc, cols, N)
    out["telemetry_check"] = telemetry_check(cols, N)
    not_run = sc.code_not_run()
    try:
        out["resimulation"] = (
            {"reproduced": None, "verdict": f"not resimulated: {not_run[0]}"} if not_run and resimulate != 0 else
            resimulation(run, limit=resimulate) if resimulate != 0 else
            {"reproduced": None, "verdict": "not resimulated (testbed resimulate checks the run)"})
    except Exception as e:  # noqa: BLE001 - the report stands without it; say why
        out["resimulation"] = {"reproduced": None, "verdict": f"not resimulated: {type(e).__name__}: {e}"}
    last_t = (cols.last_log_time - start.t0_ns) / 1e9 if start and cols.last_log_time else None
    try:
        overrides = json.loads(runmeta.get("scenario_overrides", "{}") or "{}")
    except ValueError:
        overrides = None
    out["recording"] = {
        "path": str(path), "source": cols.source, "truncated": cols.truncated, "read_error": cols.read_error,
        "complete": not cols.truncated and "testbed.recorder" in cols.metadata,
        "messages": dict(cols.counts), "last_message_s": last_t, "duplicates": cols.duplicates,
        "malformed": cols.malformed, "rejected": dict(cols.rejected), "events_not_kept": cols.not_kept,
        "software": cols.metadata.get("testbed.software", {}),
        "recorder": cols.metadata.get("testbed.recorder"),
        "scenario_ref": cols.metadata.get("testbed.scenario", {}).get("ref"),
        "overrides": overrides,
        "security": _security(runmeta),
    }
    out["recording"].update(recording_end(path, out["recording"], out.get("samples")))
    out["plant_source"] = getattr(cols, "plant_source", None)
    out["model_source"] = getattr(cols, "model_source", None)
    return out


def recording_end(path: str | Path, rec: dict, samples: int | None) -> dict:
    """Where an incomplete recording ends and why: ``ends`` (a sentence, None when complete) and ``error``
    (what the recorder wrote beside it, ``PATH.error``, when it could not write the file)."""
    from ..record.recording import error_path

    err = None
    try:
        err = json.loads(error_path(path).read_text())
    except (OSError, ValueError):
        pass
    if rec["complete"] and err is None:
        return {"ends": None, "error": None}
    at = f"after {samples} samples" + (f" (last message at {rec['last_message_s']:.3f} s)"
                                       if rec.get("last_message_s") is not None else "")
    why = (f"the recorder could not write it: {err.get('error')} ({error_path(path).name})" if isinstance(err, dict)
           else "no footer: the recorder did not finish (killed, or its host stopped)")
    return {"ends": f"ends {at}; {why}", "error": err}


def plot(run: Run, path: str | Path, *, title: str = "", size: str = "page") -> Path:
    """The paper's Fig. 2 of a recording's ``Run``: states, input, E_k at encoder and decoder, the DoS
    intervals of its ``dos`` section shaded."""
    from ..analysis.figures import plot_time_series, series_of_run

    kind = {"live": "live run", "simulate": "simulation"}.get(run.source, run.source)
    return plot_time_series(series_of_run(run), path, title=title or f"{run.scenario.name}, {kind}",
                            intervals=run.summary["dos"]["intervals"], size=size)
