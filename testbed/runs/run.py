"""The Python API for notebooks: ``testbed.open(PATH)`` and ``testbed.simulate(SCENARIO, **overrides)``.

Both return a :class:`Run`: the scenario, one numpy array per quantity with one
entry per sample k (``arrays``), the events, the timing summary, the results
(``summary``: ``SUMMARY_KEYS``, and ``RECORDING_KEYS`` / ``LIVE_KEYS`` for recordings),
``save(path)`` (a recording), ``plot(path)`` (the figure of ``testbed simulate --plot``), and
``to_pandas()`` / ``to_polars()`` when those libraries are installed::

    import testbed
    run = testbed.open("recordings/paper.mcap")     # a recording of testbed run / simulate --out
    run.arrays["E"][:5], run.arrays["theta"].sum()
    sim = testbed.simulate("paper", x0=[0.2, 0.0], E0=0.2, M=8, duration=10)
    sim.save("variant.mcap"); sim.plot("variant.pdf", size="column")
    df = sim.to_pandas()

The array names follow the paper and ``testbed simulate --json``: ``k``, ``t``
(t_k = k T), ``x`` (N, n), ``u`` (N, m), ``q`` (q_k at the decoder), ``xi`` and
``E`` (xi_k, E_k at the encoder, Algorithm 1), ``xi_dec`` and ``E_dec`` (at the
decoder, Algorithm 2), ``q_enc``, ``theta``, ``symbols``, ``saturated``,
``attack_on``, ``dropped``; for live runs also the timing in seconds
(``t_sample``, ``jitter``, ``delay``, ``sensor_to_actuator``, ``stage_encoder``,
``stage_proxy``, ``stage_controller``, ``stage_plant``) and the flags
``deadline_miss``, ``u_missing``.  NaN marks what a run did not record.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..common.errors import BadInput
from ..record.tracereader import read_recording_trace

if TYPE_CHECKING:

    from ..record.columns import Columns
    from ..scenario import Scenario
    from ..sim.loop import SimResult

#: ``Run.summary`` of every run, live or simulated (the scalar keys of ``testbed simulate --json``;
#: docs/api.md explains each)
SUMMARY_KEYS = ("scenario", "plant", "model", "plant_params", "model_params", "n", "m", "T", "M", "Lambda", "mode",
                "bits", "K", "timing_mode", "rule", "packets_dropped", "dos_intervals", "saturations", "withheld_at",
                "encoder_decoder_agree", "x_final", "final_norm", "converged", "escaped", "diverged", "diverged_at",
                "plant_fault", "plant_fault_at", "method_fault", "method_fault_at", "lockstep_breaks", "method",
                "max_norm", "samples_lost", "simulator", "losses")
#: ``Run.summary`` of a recording (``testbed.open``), live or simulated, besides ``SUMMARY_KEYS``
RECORDING_KEYS = ("source", "run_id", "t0_ns", "samples", "complete", "outcome", "dos", "loss_reasons",
                  "dropped_by_attacker", "agreement")
#: ``Run.summary`` of a live run only (what only a run over the network can report)
LIVE_KEYS = ("deadline", "ack_via_attacker", "controller_lost_at", "late_symbols", "invalid_payloads", "faults",
             "events", "attacker")


class MissingExtra(ImportError):
    """An optional library a method needs is not installed (one line says which)."""


@dataclass
class Run:
    """One run, live or simulated, as arrays (see the module docstring)."""

    scenario: Scenario
    arrays: dict[str, np.ndarray]
    events: list[dict] = field(default_factory=list)
    timing: dict | None = None
    summary: dict = field(default_factory=dict)
    source: str = "simulate"
    path: str | None = None
    metadata: dict[str, dict] = field(default_factory=dict)
    #: the overrides the run was simulated with (``testbed.simulate``), stored by ``save``
    overrides: dict = field(default_factory=dict)
    _result: SimResult | None = field(default=None, repr=False)  # the simulator's SimResult (``save`` records it)
    _columns: Columns | None = field(default=None, repr=False)  # a recording's columns (``testbed report`` reads them)
    _details: dict | None = field(default=None, repr=False)  # a recording's whole summary (``recording_summary``)

    @property
    def recorded_columns(self) -> Columns | None:
        """A recording's columns as read (``testbed.record.columns``; None for a simulated run): what
        ``testbed report`` and the resimulation read beyond the arrays."""
        return self._columns

    @property
    def recorded_summary(self) -> dict | None:
        """A recording's whole summary (``recording_summary``; None for a simulated run)."""
        return self._details

    @property
    def N(self) -> int:
        """The number of samples."""
        return len(self.arrays["k"])

    def __repr__(self) -> str:
        where = f" from {self.path}" if self.path else ""
        return (f"Run({self.source}{where}: scenario {self.scenario.name}, {self.N} samples of T = "
                f"{self.scenario.T:g} s, {int(np.sum(self.arrays['theta']))} lost)")

    def save(self, path: str | Path, *, overwrite: bool = False) -> Path:
        """Write the run as an MCAP recording (what ``testbed simulate --out`` writes; every reader and
        viewer opens it: ``testbed.open``, ``testbed report``, ``testbed replay``, Foxglove).

        A simulated run is recorded with its scenario and overrides; a run opened from a recording
        is copied as it is.  An existing file is a ``BadInput`` unless ``overwrite``.
        """
        path = Path(path)
        if path.exists() and not overwrite:
            raise BadInput(f"{path} exists: pass overwrite=True to replace it")
        if self._result is not None:
            from ..record.recording import record_simulation

            path.parent.mkdir(parents=True, exist_ok=True)
            record_simulation(path, self.scenario, self._result, overrides=dict(self.overrides),
                              ref=self.scenario.path or self.scenario.name, exclusive=not overwrite)
            return path
        if self.path is not None:
            import shutil

            if Path(self.path).resolve() != path.resolve():
                path.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(self.path, path)
            return path
        raise BadInput("this Run has neither a simulation nor a recording behind it: nothing to save")

    def plot(self, path: str | Path, *, size: str = "page", title: str | None = None) -> Path:
        """Draw the run as ``testbed simulate --plot`` does (states, input, E_k at both ends, DoS shaded):
        ``.png``, ``.pdf`` or ``.svg`` by the extension; ``size`` ``"column"`` or ``"page"`` (IEEE widths)."""
        from ..analysis.figures import figure_title, plot_time_series, series_of_run
        from ..common import figstyle

        figstyle.check_path(path)
        figstyle.check_size(size)
        ivs = self.summary.get("dos_intervals")
        return plot_time_series(series_of_run(self), path, intervals=ivs, size=size,
                                title=figure_title(self.scenario) if title is None else title)

    def resimulate(self, plant: str = "auto", limit: int | None = None) -> dict:
        """Re-run a recording's loop in the simulator and compare it with the recording: the dict of
        ``testbed resimulate --plant PLANT --json`` (the ``resimulation`` section of ``testbed report``):
        ``plant`` ("model" or "recorded"), ``loop_identical``, ``loop_first_divergence``,
        ``plant_model_error``, ``reproduced``, ``verdict``, ...  ``plant``: "auto" (the recorded plant
        when the plant was an external node or a declared device, else the model), "model" or "recorded";
        ``limit``: samples 0 .. limit - 1 only.  A simulated ``Run`` (``testbed.simulate``) has no
        recording to compare with: ``BadInput``.  The run's own code must have been trusted
        (``open(..., trust_code=True)`` where the recording stores it): ``plants.refs.CodeNotTrusted``."""
        if self._columns is None:
            raise BadInput("resimulate: this Run is not a recording (save it and testbed.open it)")
        from .resimulate import PLANTS, resimulation

        if plant not in PLANTS:
            raise BadInput(f"plant={plant!r}: expected one of {', '.join(PLANTS)}")
        return resimulation(self, plant=plant, limit=limit)

    def columns(self) -> dict[str, np.ndarray]:
        """Flat 1-D columns, one row per sample: vectors as x1..xn, u1..um, ... (what ``export`` writes)."""
        return flat_columns(self.arrays)

    def to_pandas(self) -> Any:
        """A ``pandas.DataFrame``, one row per sample (``columns()``)."""
        return self._frame("pandas")

    def to_polars(self) -> Any:
        """A ``polars.DataFrame``, one row per sample (``columns()``)."""
        return self._frame("polars")

    def _frame(self, library: str) -> Any:
        import importlib

        try:
            lib = importlib.import_module(library)
        except ImportError:
            raise MissingExtra(f"to_{library}() needs {library}: pip install {library} "
                               "(or pip install 'dos-testbed[dataframes]')") from None
        return lib.DataFrame(self.columns())


def column_names(arrays: dict[str, np.ndarray]) -> list[str]:
    """The names ``flat_columns`` gives, from the arrays' shapes alone."""
    out = []
    for name, a in arrays.items():
        shape = np.shape(a)
        out += [f"{name}{j + 1}" for j in range(shape[1])] if len(shape) == 2 else [name]
    return out


def flat_columns(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Vectors (N, w) become columns name1..namew; the rest stay as they are."""
    out = {}
    for name, a in arrays.items():
        a = np.asarray(a)
        if a.ndim == 2:
            for j in range(a.shape[1]):
                out[f"{name}{j + 1}"] = np.ascontiguousarray(a[:, j])
        else:
            out[name] = a
    return out


# ============================================================================ from a recording
def _ns_to_s(a: np.ndarray, ok: np.ndarray) -> np.ndarray:
    from ..wire import messages as msg

    ok = ok & (a != msg.NO_TIME)
    out = np.full(a.shape, np.nan)
    out[ok] = a[ok] / 1e9
    return out


def _timing_arrays(cols: Columns, N: int, T: float) -> dict[str, np.ndarray]:
    from ..wire import messages as msg

    g = cols.get
    P, EN, C, A = (cols.has(r)[:N] for r in ("plant", "encoder", "controller", "attacker"))
    t_ns, u_rx = g("plant", "t_ns")[:N], g("plant", "u_rx_ns")[:N]
    e_tx, c_tx, a_tx = g("encoder", "tx_ns")[:N], g("controller", "tx_ns")[:N], g("attacker", "tx_ns")[:N]

    def diff(a: np.ndarray, b: np.ndarray, ok: np.ndarray) -> np.ndarray:
        ok = ok & (a != msg.NO_TIME) & (b != msg.NO_TIME)
        out = np.full(N, np.nan)
        out[ok] = (a[ok] - b[ok]) / 1e9
        return out

    t_sample = _ns_to_s(t_ns, P)
    flags = g("plant", "flags")[:N]
    return {
        "t_sample": t_sample,
        "jitter": t_sample - np.arange(N) * T,
        "delay": np.where(P, g("plant", "delay_ns")[:N] / 1e9, np.nan),
        "sensor_to_actuator": diff(u_rx, t_ns, P & (g("plant", "theta")[:N] == 0)),
        "stage_encoder": diff(e_tx, t_ns, EN & P & (g("encoder", "silent")[:N] == 0)),
        "stage_proxy": diff(a_tx, e_tx, A & EN),
        "stage_controller": diff(c_tx, a_tx, A & C & (g("controller", "reason")[:N] == 0)),
        "stage_plant": diff(u_rx, c_tx, C & P),
        "deadline_miss": P & (flags & msg.PlantTelemetry.FLAG_MISS != 0),
        "u_missing": P & (flags & msg.PlantTelemetry.FLAG_NO_U != 0),
    }


def run_of_recording(cols: Columns, sc: Scenario, path: str | Path | None = None) -> Run:
    """A :class:`Run` from a recording's columns (``testbed.record.columns.Columns``) and its scenario;
    ``Run.path`` is ``path`` as given (default: the columns').

    ``Run.summary`` comes from ``testbed.record.sections.recording_summary``; the whole of it and the
    columns stay with the run (``testbed report`` adds its own sections from them).
    """
    from ..record.sections import recorded_attack, recording_summary
    from ..wire import messages as msg

    s = recording_summary(cols, sc)
    N = s["samples"]
    attack_on, dropped = recorded_attack(cols, N)  # the attacker's own log
    sat = np.zeros(N, dtype=bool)
    sat[np.asarray(s["saturated_at"], dtype=np.int64)] = True
    arrays = {
        "k": np.arange(N), "t": np.asarray(s["t"]), "x": s["x"], "u": s["u"], "q": s["q"], "xi": s["xi"],
        "E": s["E"], "E_dec": s["E_dec"], "xi_dec": s["xi_dec"], "q_enc": cols.get("encoder", "q")[:N],
        "theta": np.asarray(s["theta"]), "symbols": np.asarray(s["symbols"], dtype=np.int64), "saturated": sat,
        "attack_on": attack_on, "dropped": dropped,
    }
    if s.get("x_meas") is not None:  # what the sensor read ([plant.sensor])
        arrays["x_meas"] = s["x_meas"]
    live = cols.source == "live"
    if live:
        arrays.update(_timing_arrays(cols, N, sc.T))
    events = [{"k": e.k, "t": None if e.t_ns == msg.NO_TIME else e.t_ns / 1e9, "node": e.node, "kind": e.kind,
               "detail": e.detail} for e in cols.events]
    keyed = dict(s, t0_ns=cols.start.t0_ns if cols.start else None)
    keys = SUMMARY_KEYS + RECORDING_KEYS + (LIVE_KEYS if live else ())
    summary = {k: keyed[k] for k in keys if k in keyed}
    return Run(scenario=sc, arrays=arrays, events=events, timing=s.get("timing"), summary=summary,
               source=cols.source, path=str(cols.path if path is None else path), metadata=cols.metadata,
               _columns=cols, _details=s)


def open(path: str | Path, *, trust_code: bool = False) -> Run:  # noqa: A001 - testbed.open, as the issue names it
    """A recording (``testbed run`` or ``testbed simulate --out``) as a :class:`Run`.

    A plant or method module the recording names is imported as the run did (your own code, from the
    recorded scenario's folder or ``sys.path``).  When it is not importable, the source stored in the
    recording is code from whoever made the file: it runs only with ``trust_code=True`` (the
    commands' ``--trust-code``).  Without it the arrays, the summary from the recorded values and the
    plots are all there; what needs the code (``Run.scenario.code_not_run()`` says what) is skipped:
    ``summary["escaped"]`` is None, and simulating the scenario raises ``plants.refs.CodeNotTrusted``.

    Raises ``testbed.common.errors.BadInput`` for a file that is not a usable recording.
    """
    from ..common import compilenotice, gcpasses

    with gcpasses.fewer_passes():  # numba's start and the read (the caller's threshold is put back)
        from ..record.summary import load

        compilenotice.install()
        # the fields the arrays, the summary and the resimulation read (q_k at the encoder; the stage times of a
        # live run), as ``testbed report`` reads them, and no other: the columns are the memory of a long recording
        cols, sc = load(path, trust_code=trust_code)
        return run_of_recording(cols, sc, path)


# ============================================================================ from the simulator
def run_of_simulation(sc: Scenario, res: SimResult, overrides: dict | None = None, *,
                      summary: dict | None = None) -> Run:
    """A :class:`Run` from ``testbed.sim.batch.simulate_scenario``'s result; ``summary``: its
    ``testbed.sim.batch.summarize(sc, res)`` when the caller has made it already."""
    from ..sim.batch import attack_on_samples, attacker_drops, summarize

    N = len(res.t)
    u = res.u if res.u_plant is None else res.u_plant  # what acted (after [plant.actuator]), as recorded
    arrays = {"k": np.arange(N), "t": np.asarray(res.t), "x": res.x, "u": u, "q": res.q, "xi": res.xi_enc,
              "E": res.E_enc, "E_dec": res.E_dec, "xi_dec": res.xi_dec, "q_enc": res.q_enc,
              "theta": np.asarray(res.theta).astype(np.int64), "symbols": np.asarray(res.symbols, dtype=np.int64),
              "saturated": np.asarray(res.saturated, dtype=bool), "attack_on": attack_on_samples(sc, res),
              "dropped": attacker_drops(res)}
    if res.x_meas is not None:  # what the sensor read ([plant.sensor])
        arrays["x_meas"] = res.x_meas
    events = [{"k": int(k), "t": float(k * sc.T), "node": "encoder", "kind": "saturation",
               "detail": f"x_k outside Q(xi_k, E_k), E_k = {res.E_enc[k]:.3e}"} for k in np.flatnonzero(res.saturated)]
    s = summarize(sc, res, arrays=True) if summary is None else summary
    summary = {k: s[k] for k in SUMMARY_KEYS}
    return Run(scenario=sc, arrays=arrays, events=events, timing=None, summary=summary, source="simulate",
               overrides=dict(overrides or {}), _result=res)


def resolve_scenario(scenario: str | Path | Scenario, overrides: dict | None = None) -> Scenario:
    """A scenario object, bundled name or .toml path, with overrides applied (``BadInput`` if unusable)."""
    from .. import scenario as scen

    if isinstance(scenario, scen.Scenario):
        return scen.with_overrides(scenario, overrides or {})
    return scen.load(str(scenario), overrides=overrides, read_recording_trace=read_recording_trace)  # built once


def simulate(scenario: str | Path | Scenario, **overrides: Any) -> Run:
    """Simulate a scenario (object, bundled name or .toml path) with ``overrides`` and return a :class:`Run`.

    Overrides (validated as if written in the scenario file; ``testbed.scenario.OVERRIDES``):
    ``duration``, ``T``, ``timing``, ``deadline``, ``mode``, ``loss_fraction``, ``actuation``,
    ``rule``, ``seed``, ``method`` (these are also command-line flags; ``method`` swaps the
    coding-and-control method, docs/methods.md), ``x0``, ``E0``, ``M`` and ``attack``
    (a table merged into ``[attack]``, e.g. ``attack={"intervals": [[1.0, 2.0]]}``; a new
    ``kind`` replaces the table).  A bad override raises ``testbed.BadInput`` with what to change.
    """
    from ..common import compilenotice
    from ..sim.batch import simulate_scenario

    compilenotice.install()
    sc = resolve_scenario(scenario, overrides)
    return run_of_simulation(sc, simulate_scenario(sc), {k: v for k, v in overrides.items() if v is not None})


__all__ = ["Run", "open", "simulate", "resimulate", "flat_columns", "run_of_simulation", "run_of_recording", "MissingExtra",
           "resolve_scenario", "BadInput", "SUMMARY_KEYS", "RECORDING_KEYS", "LIVE_KEYS"]


def resimulate(path: str | Path, *, trust_code: bool = False, plant: str = "auto") -> dict:
    """``testbed resimulate PATH [--plant P] --json`` as a dict (``testbed.runs.resimulate.resimulation``).
    ``trust_code``: run a plant's or method's source stored in the recording (``open``); without it, when
    that code is needed, ``plants.refs.CodeNotTrusted`` (one line naming ``--trust-code``) and nothing is run."""
    from ..record.summary import load
    from .resimulate import resimulation

    run = run_of_recording(*load(path, trust_code=trust_code, note=False))  # the error below is the line
    return resimulation(run, plant=plant)
