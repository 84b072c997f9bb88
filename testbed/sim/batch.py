"""In-process simulators: plant, encoder, attacker and decoder/controller in lockstep.

Two entry points share one semantics (sample k = 0, ..., N-1 at t_k = k T):

1. ``simulate_loop`` - one trajectory, per sample, with *separate* encoder and
   decoder ends (``methods.EncoderEnd``, ``DecoderEnd``) that only see symbols and acks
   (what a live run does).
   Returns every per-sample quantity (``SimResult``).
2. ``simulate_batch`` - many initial states and/or schedules at once in one
   numba kernel (one core; ``testbed.analysis.parallel`` spreads batches over
   processes).  Encoder and decoder keep separate (xi, E) arrays and
   each computes its own prediction; their disagreement is counted.  Summary
   outputs always, full traces on request.  The analysis uses this.

At every sample:  x_k -> encoder symbol (Algorithm 1) -> attacker (theta_k) ->
decoder q_k, u_k = (1 - theta_k) K q_k (Algorithm 2, law (2)) -> ack theta_k ->
both ends apply (xi), (E) -> plant x_{k+1} = phi_T(x_k, u_k)."""

from __future__ import annotations

import math
from array import array
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from attackers.greedy import greedy_init

from ..loop.channel import ATTACKER, LOSS_KINDS, loss_counts_of
from ..loop.flow import DEFAULT_FLOW, FLOW_OK, FlowOptions
from ..loop.quantizer import (
    MODES,
    QuantizerParams,
)
from .kernel import COUNTS, TRACE_INTS, _batch_kernel, loop_state_width
from .loop import (  # noqa: F401 - LinkEffects, OnlineAttacker, simulate_loop: re-exported
    SCORES,
    LinkEffects,
    OnlineAttacker,
    RecordEnds,
    SimResult,
    continue_ends,
    ends_from_record,
    equal_where,
    loop_state_from_samples,
    loop_state_of,
    simulate_loop,
)
from .trajectory import simulate_scenario  # noqa: F401 - re-exported: the scenario level's entry point

if TYPE_CHECKING:
    import numpy.typing as npt

    from plants.base import Plant

    from ..methods.base import Method
    from ..scenario.spec import Scenario
    from .loop import Replay


# ============================================================================ batch simulator
@dataclass
class BatchResult:
    """Summary (always) and traces (``record=True``) of a batch run."""

    x_final: np.ndarray     # (B, n)
    E_final: np.ndarray     # (B,)
    status: np.ndarray      # (B,) FLOW_* of the plant at the stop
    stop_k: np.ndarray      # (B,) samples simulated (n_steps unless the flow diverged)
    saturations: np.ndarray  # (B,)
    mismatch: np.ndarray    # (B,) samples where encoder and decoder disagreed
    max_norm: np.ndarray    # (B,) max ||x_k||_inf over the run
    attacked: np.ndarray    # (B,) number of samples with theta_k = 1
    state_final: np.ndarray | None = None  # (B, W) both ends' state at the stop (``loop_state_width`` layout)
    x: np.ndarray | None = None      # (B, N, n) x_k
    E: np.ndarray | None = None      # (B, N) E_k at the encoder
    theta: np.ndarray | None = None  # (B, N)

    @property
    def final_norm(self) -> np.ndarray:
        return np.max(np.abs(self.x_final), axis=1)

    def converged(self, tol: float = 1e-4) -> np.ndarray:
        return (self.status == FLOW_OK) & (self.final_norm < tol)


def simulate_batch(plant: Plant, K: npt.ArrayLike, qp: QuantizerParams, X0: npt.ArrayLike, n_steps: int, *,
                   model: Plant | None = None, theta: npt.ArrayLike | None = None,
                   sched_idx: npt.ArrayLike | None = None, timing: Sequence[float] | np.ndarray | None = None,
                   latency: npt.ArrayLike | None = None, latency_idx: npt.ArrayLike | None = None,
                   u_max: float = math.inf, greedy_params: npt.ArrayLike | None = None,
                   score: str = "state", mode: str | None = None, record: bool = False,
                   flow: FlowOptions = DEFAULT_FLOW, specialize: bool = False, init_state: npt.ArrayLike | None = None,
                   stop: tuple[float, float, float] | None = None, method: Method | None = None) -> BatchResult:
    """Vectorized lockstep simulation of B trajectories (numba, one core).

    Parameters
    ----------
    plant, K, qp : the loop (K is m x n); ``plant`` is the true plant the state follows
    X0 : (B, n) initial states (or (n,) for one)
    n_steps : number of samples N
    model : the plant model of the encoder's and decoder's predictions (rule (xi));
        default ``plant`` (no model mismatch)
    theta : (S, N') 0/1 attack table, S schedules (rows shorter than N are padded
        with 0); ``sched_idx`` (B,) picks each trajectory's row (default: row b if
        S == B, else row 0).  None: no attack.
    timing : physical timing as ``Scenario.timing_params`` gives it ([physical, scheduled,
        delta_s, d T, loss deadline] in ns); None: ideal timing (u_k acts from t_k)
    latency : physical timing: (D, N) latencies [ns] of u_k after t_k (a lost sample's after
        the loss deadline; a scalar or (N,) is broadcast), ``latency_idx`` (B,) picks each
        trajectory's row (default as for ``sched_idx``)
    u_max : actuator limit: |u_k| is clamped to it (a non-finite u_k is not applied), as
        the live plant does (``[controller] u_max``)
    greedy_params : [kappa_F, rho_F, kappa_D, rho_D, threshold] (shape (5,), or (B, 5)
        for one budget per trajectory) to run the online greedy attacker instead (``score`` "state" or "E" is what it maximizes).
    mode : "ideal" | "resilient" | "none" (no quantization: the nominal loop);
        default qp.mode.
    record : keep x_k, E_k and theta_k for every sample.
    specialize : run the kernel specialized for this plant (its right-hand side
        inlined, about twice the throughput).  Generated and cached on disk by
        ``testbed.sim.kernelcache``: the first use per plant compiles for a few
        seconds, later processes load it.  Falls back to the generic kernel
        (one log line) for a plant whose right-hand side is not a module-level
        ``@rhs_function``.  Results are identical either way.
    init_state : (B, W) both ends' state (xi, E, u_{k-1}; ``loop_state_width`` layout) to start from
        instead of xi_0 = 0, E_0 = ``qp.E0``, u_{-1} = 0 (the continuation of a loop).
    stop : (x_tol, E_tol, x_out): a trajectory stops at the first sample with ||x_k||_inf <
        x_tol and E_k < E_tol at both ends, or with ||x_k||_inf > x_out (``stop_k`` is that sample).
    method : a bundled method (``testbed.methods``) to run instead of the paper's (``mode`` is then
        the method's); a method without a kernel (a user's) raises ``ValueError``.
    """
    X0 = np.ascontiguousarray(np.atleast_2d(np.asarray(X0, dtype=np.float64)))
    B, n = X0.shape
    if n != plant.n:
        raise ValueError(f"X0 has {n} columns, plant {plant.name} has n = {plant.n}")
    N = int(n_steps)
    Kg = np.ascontiguousarray(np.asarray(K, dtype=np.float64).reshape(plant.m, plant.n))
    if theta is None:
        tab = np.zeros((1, 0), dtype=np.uint8)
    else:
        tab = np.ascontiguousarray(np.atleast_2d(np.asarray(theta, dtype=np.uint8)))
    if sched_idx is None:
        sched_idx = np.arange(B) if tab.shape[0] == B else np.zeros(B, dtype=np.int64)
    # a copy, writable: the kernel is typed (and cached) once, not again for a read-only broadcast
    sched_idx = np.array(np.broadcast_to(np.asarray(sched_idx, dtype=np.int64), (B,)))
    if sched_idx.size and (sched_idx.max() >= tab.shape[0] or sched_idx.min() < 0):
        raise ValueError("sched_idx points outside the theta table")
    if greedy_params is None:
        gp = np.zeros((0, 5))
    else:
        gp = np.asarray(greedy_params, dtype=np.float64)
        gp = np.ascontiguousarray(np.broadcast_to(gp, (B, 5)) if gp.ndim == 1 else gp)
        if gp.shape != (B, 5):
            raise ValueError(f"greedy_params must have shape (5,) or ({B}, 5), got {gp.shape}")
    if timing is None or int(timing[0]) == 0:
        tpar = np.zeros(5, dtype=np.int64)
        ltab = np.zeros((0, 0), dtype=np.int64)
        latency_idx = np.zeros(B, dtype=np.int64)
    else:
        tpar = np.ascontiguousarray(np.asarray(timing, dtype=np.int64))
        ltab = np.zeros(N, dtype=np.int64) if latency is None else np.asarray(latency, dtype=np.int64)
        if ltab.ndim <= 1:
            ltab = np.broadcast_to(ltab, (N,)).reshape(1, N)
        ltab = np.ascontiguousarray(ltab)
        if ltab.ndim != 2 or ltab.shape[1] < N:
            raise ValueError(f"latency must have N = {N} columns, got shape {ltab.shape}")
        if latency_idx is None:
            latency_idx = np.arange(B) if ltab.shape[0] == B else np.zeros(B, dtype=np.int64)
        latency_idx = np.ascontiguousarray(np.broadcast_to(np.asarray(latency_idx, dtype=np.int64), (B,)))
        if latency_idx.max() >= ltab.shape[0] or latency_idx.min() < 0:
            raise ValueError("latency_idx points outside the latency table")
    model = plant if model is None else model
    if (model.n, model.m) != (plant.n, plant.m):
        raise ValueError(f"model {model.name} (n={model.n}, m={model.m}) does not match plant {plant.name} "
                         f"(n={plant.n}, m={plant.m})")
    mode_code = MODES[mode or qp.mode]
    dpar = qp.dpar
    E0 = float(qp.E0)
    if method is None:
        method = getattr(qp, "method", None)   # ``methods.base.MethodQuantizerParams``
    if method is not None and mode is None:
        code = method.kernel_code(qp)
        if code is None:
            raise ValueError(f"method {method.display_name()!r} has no batch kernel (a user's method runs in "
                             "the per-sample simulator and live only)")
        mode_code = code
        E0 = float(method.kernel_E0(qp))
        if mode_code == 4:
            dpar = np.zeros(4)
    shp = (B, N) if record else (0, 0)
    X_rec = np.zeros(shp + (n,)) if record else np.zeros((0, 0, n))
    E_rec = np.zeros(shp)
    th_rec = np.zeros(shp, dtype=np.uint8)
    out: dict[str, Any] = dict(x_final=np.zeros((B, n)), E_final=np.zeros(B), status=np.zeros(B, np.int8),
               stop_k=np.zeros(B, np.int64), saturations=np.zeros(B, np.int64),
               mismatch=np.zeros(B, np.int64), max_norm=np.zeros(B), attacked=np.zeros(B, np.int64))
    W = loop_state_width(plant.n, plant.m)
    if init_state is None:
        ist = np.zeros((0, W))
    else:
        ist = np.ascontiguousarray(np.asarray(init_state, dtype=np.float64).reshape(B, W))
    spar = np.zeros(3) if stop is None else np.asarray(stop, dtype=np.float64).reshape(3)
    out["state_final"] = np.zeros((B, W))
    kernel = _batch_kernel
    if specialize:
        from .kernelcache import specialized

        kernel = specialized(_batch_kernel, {"rhs": type(plant).rhs, "rhs_m": type(model).rhs})
    rhs, rhs_m = type(plant).rhs.cfunc, type(model).rhs.cfunc
    kernel(rhs, plant.p, rhs_m, model.p, float(qp.T), flow.as_array(), Kg, X0, E0, int(qp.M),
           float(qp.Lambda), mode_code, float(qp.sigma), float(qp.E_min), dpar, float(u_max), tab, sched_idx,
           tpar, ltab, latency_idx, gp, greedy_init(), SCORES[score], N, bool(record), X_rec, E_rec, th_rec,
           out["x_final"], out["E_final"], out["status"], out["stop_k"], out["saturations"], out["mismatch"],
           out["max_norm"], out["attacked"], ist, spar, out["state_final"], np.zeros((4, 0), dtype=np.int64),
           np.zeros((0, 0, 0)), np.zeros((0, 0, TRACE_INTS), dtype=np.int64), np.zeros((B, COUNTS), dtype=np.int64))
    res = BatchResult(**out)
    if record:
        res.x, res.E, res.theta = X_rec, E_rec, th_rec
    return res


# ============================================================================ scenario level
def in_nominal_roa(plant: Plant, K: npt.ArrayLike, T: float, X: npt.ArrayLike, horizon: float = 60.0, tol: float = 1e-4,
                   flow: FlowOptions = DEFAULT_FLOW) -> np.ndarray:
    """Whether each state of X (B, n) lies in the nominal region of attraction.

    Nominal: no quantization and no DoS, u_k = K x_k (sampled data, held for T).
    A state is in the region when the nominal loop from it reaches
    ||x||_inf < tol within ``horizon`` seconds.
    """
    qp = QuantizerParams(T=T, M=2, L=0.0, E0=1.0, mode="none")
    res = simulate_batch(plant, K, qp, X, int(round(horizon / T)), mode="none", flow=flow)
    return res.converged(tol)


# ============================================================================ the escape criterion
#: seconds the loop is continued without attack after the horizon (``EscapeCriterion.horizon_s``)
ESCAPE_HORIZON = 60.0


@dataclass(frozen=True)
class EscapeCriterion:
    """When a run has *escaped*: judged by the quantized loop itself, continued without attack.

    From the state the run ended in (the plant's x_N and both ends' xi_N, E_N, u_{N-1}), the
    whole loop (encoder, controller with its decoder, plant; ideal timing, the scenario's
    quantizer and rule) runs on with theta_k = 0 for at most ``horizon_s`` seconds.  It
    *recovers* when it reaches ||x_k||_inf < ``x_tol`` with E_k < ``E_tol`` at both ends; it
    stops early when the flow diverges or ||x_k||_inf exceeds ``x_out``, the radius of the box
    on which the model's Lipschitz bound holds (``lipschitz_region``; outside it the
    quantizer's growth rate Lambda = e^{L T} is not guaranteed).  The run has escaped when the
    loop did not recover within the horizon (also: the attacked run itself diverged).
    """

    horizon_s: float = ESCAPE_HORIZON
    x_tol: float = 1e-4
    E_tol: float = 1e-4
    x_out: float = math.inf
    kind: str = "quantized loop continued without attack"

    @classmethod
    def for_loop(cls, model: Plant, qp: QuantizerParams, tol: float = 1e-4,
                 horizon_s: float = ESCAPE_HORIZON) -> EscapeCriterion:
        """The criterion of a loop: x_tol = ``tol`` (``[run] converge_tol``), E_tol = max(tol, 2 E_min)
        (E_k cannot fall below the floor E_min), x_out = the model's ``lipschitz_region``."""
        return cls(float(horizon_s), float(tol), max(float(tol), 2.0 * float(qp.E_min)),
                   float(getattr(model, "lipschitz_region", math.inf)))

    def to_dict(self) -> dict:
        """The JSON key ``escape_criterion``."""
        return {"kind": self.kind, "horizon_s": self.horizon_s, "x_tol": self.x_tol, "E_tol": self.E_tol,
                "x_out": None if math.isinf(self.x_out) else self.x_out}

    def steps(self, T: float) -> int:
        return int(round(self.horizon_s / T))


def _batch_runner(plant: Plant, K: npt.ArrayLike, qp: QuantizerParams, model: Plant, flow: FlowOptions,
                  method: Method | None = None) -> Callable[[np.ndarray, np.ndarray, int, tuple[float, float, float]],
                                                            dict]:
    def run(X: np.ndarray, S: np.ndarray, n_steps: int, stop: tuple[float, float, float]) -> dict:
        r = simulate_batch(plant, K, qp, X, n_steps, model=model, flow=flow, init_state=S, stop=stop, method=method)
        return {"x_final": r.x_final, "status": r.status, "state_final": r.state_final}
    return run


def judge_escape(plant: Plant, K: npt.ArrayLike, qp: QuantizerParams, x_final: npt.ArrayLike,
                 state_final: npt.ArrayLike, status: npt.ArrayLike, criterion: EscapeCriterion, *,
                 model: Plant | None = None, flow: FlowOptions = DEFAULT_FLOW,
                 run: Callable[[np.ndarray, np.ndarray, int, tuple[float, float, float]], dict] | None = None,
                 method: Method | None = None) -> np.ndarray:
    """Whether each run escaped (:class:`EscapeCriterion`): (B,) bool.

    Parameters
    ----------
    plant, K, qp : the loop (``plant`` the true plant, ``model`` the predictions' model).
    x_final : (B, n) x_N; state_final : (B, W) both ends' state at N (``loop_state_width``,
        ``BatchResult.state_final``, :func:`loop_state_of`); status : (B,) flow status of the run
        (not FLOW_OK: it diverged, hence escaped).
    run : how the continuation runs, ``run(X, S, n_steps, stop) -> {"x_final", "status",
        "state_final"}`` (default: ``simulate_batch`` here; the analysis passes its parallel map).
        Every caller judges with this function, so the per-sample and the batch paths agree
        bit for bit.
    """
    model = plant if model is None else model
    x_final = np.atleast_2d(np.asarray(x_final, dtype=np.float64))
    B = x_final.shape[0]
    esc = np.asarray(status).reshape(B) != FLOW_OK
    go = np.flatnonzero(~esc)
    if go.size:
        run = run or _batch_runner(plant, K, qp, model, flow, method)
        S = np.atleast_2d(np.asarray(state_final, dtype=np.float64))[go]
        c = criterion
        out = run(x_final[go], S, c.steps(qp.T), (c.x_tol, c.E_tol, c.x_out))
        n, m = plant.n, plant.m
        sf = out["state_final"]
        rec = ((out["status"] == FLOW_OK) & (np.max(np.abs(out["x_final"]), axis=1) < c.x_tol)
               & (sf[:, n] < c.E_tol) & (sf[:, 2 * n + 1 + m] < c.E_tol))
        esc[go] = ~rec
    return esc


def _all_finite_numbers(o: list) -> bool:
    """A (nested) list of plain numbers without NaN or inf: nothing to clean (checked in C)."""
    try:
        a = np.asarray(o)
    except ValueError:  # ragged
        return False
    if a.dtype.kind == "f":
        return bool(np.isfinite(a).all())
    return a.dtype.kind in "biu"


def json_clean(o: Any) -> Any:
    """NaN -> None, recursively (JSON has no NaN)."""
    if isinstance(o, float):
        return o if math.isfinite(o) else None
    if isinstance(o, list):
        if len(o) > 64 and _all_finite_numbers(o):
            return o
        return [json_clean(v) for v in o]
    if isinstance(o, dict):
        return {k: json_clean(v) for k, v in o.items()}
    return o


def plant_and_model(sc: Scenario) -> dict:
    """The true plant and the model of a scenario by name and parameters (the JSON outputs name both).

    ``plant``: what the simulator and the live plant node integrate (``[plant]``; "fmu:FILE"
    for an FMU, whose ``plant_params`` are the FMU parameters set); ``model``: what the
    predictions, the design and the analysis use (``[model]``, default ``[plant]``).
    """
    model = sc.make_model()
    pparams = dict(sc.plant.params) if sc.plant.fmu is not None else sc.make_plant().params_dict()
    return {"plant": sc.plant.name, "model": model.name, "plant_params": pparams,
            "model_params": model.params_dict()}


def escaped_run(sc: Scenario, res: SimResult, criterion: EscapeCriterion, replay: Replay | None = None, *,
                record: tuple[int, Callable[[], Iterable[tuple[int, np.ndarray, Replay]]]] | None = None) -> bool:
    """The escape verdict of one run of scenario ``sc``: every reader's (``testbed simulate``, ``run``,
    ``report``, ``testbed.open``, ``versus``, campaign rows and ``--verify``), for every method.

    It reads the run's per-sample record only (what a simulation and its recording, or a live run
    and its recording, hold alike; never the simulator's in-memory end state): both ends of the
    run's method are rebuilt from it (:func:`testbed.sim.loop.ends_from_record`, ``replay``: what a
    recording's columns say happened, default the record's own), then the loop is continued from x_N
    without attack (:class:`EscapeCriterion`): by the batch kernel for a bundled method
    (:func:`judge_escape`), by the method's own ends for a user's (``continue_ends``).  A run whose flow
    diverged, or whose method faulted, escaped.

    ``record``: (N, the record a chunk at a time: ``chunks() -> iter((k0, X, replay))``, X: x_k, or x_meas,k
    where a sensor read it); ``res`` then needs only its last two samples (:class:`RunTally`). Default: ``res``.
    """
    if res.flow_status != FLOW_OK or res.method_fault is not None:
        return True
    model = sc.make_model()
    plant = model if sc.plant.fmu is not None else sc.make_plant()
    method = sc.make_method()
    st = None
    if sc.method.name == "paper":  # its ends' state follows from the last sample (equal to the replay's, cheaper)
        st = loop_state_from_samples(res, model, sc.quantizer, sc.flow)
    if st is None:
        try:
            if record is None:
                ends = ends_from_record(res, method, model, res.K, sc.quantizer, sc.flow, replay)
            else:
                rec = RecordEnds(method, model, res.K, sc.quantizer, sc.flow, record[0])
                for k0, X, rp in record[1]():
                    rec.feed(k0, X, rp)
                ends = rec.ends()
        except Exception:  # noqa: BLE001 - a method that raises on its own record: the loop cannot go on
            return True
        if method.kernel_code(sc.quantizer) is None:  # a user's method: its own ends, continued per sample
            return continue_ends(plant, res.x_final, ends, criterion, sc.T, sc.flow, sc.controller.u_max)
        st = loop_state_of(*ends)
    return bool(judge_escape(plant, res.K, sc.quantizer, res.x_final[None, :], st[None, :], [FLOW_OK], criterion,
                             model=model, flow=sc.flow, method=None if sc.method.name == "paper" else method)[0])


def outcome_text(s: dict) -> str:
    """The outcome of a run in words, from its summary (``summarize``'s keys): what ``testbed simulate``,
    ``testbed run`` and ``testbed report`` print after the final norm."""
    if s.get("method_fault") is not None:
        return f"METHOD FAULT at sample {s['method_fault_at']}: the run ended there"
    if s.get("plant_fault") is not None:
        return f"PLANT FAULT at sample {s['plant_fault_at']}: the run ended there"
    if s.get("converged"):
        return "converged"
    if s.get("escaped"):
        return "ESCAPED" + (f" (flow diverged at sample {s['diverged_at']})" if s.get("diverged") else "")
    return "not converged"


def attacker_drops(res: SimResult) -> np.ndarray:
    """Per sample: the attacker dropped it (``res.loss_cause``; without one, every lost sample)."""
    theta = np.asarray(res.theta, dtype=bool)
    return theta if res.loss_cause is None else np.asarray(res.loss_cause) == ATTACKER


def attack_on_samples(sc: Scenario, res: SimResult) -> np.ndarray:
    """Per sample: the DoS schedule is active at t_k, or the attacker dropped sample k (an online
    attacker is on when it drops). A loss of another cause (a ``[network]`` link, a late symbol, a
    withheld one: ``res.loss_cause``) is not an attack, as the live attacker's own log has it."""
    dropped = attacker_drops(res)
    N = len(dropped)
    sched = sc.attack.schedule(sc.T, max(N, 1) * sc.T)
    if sched is None or not N:
        return dropped.copy()
    return np.asarray(sched.theta_samples(sc.T, N), dtype=bool) | dropped


def summarize(sc: Scenario, res: SimResult, *, arrays: bool = False, replay: Replay | None = None) -> dict:
    """The JSON document of ``testbed simulate --json`` (keys shared with ``testbed report``).

    ``escaped``: the loop continued without attack from where the run ended does not
    recover (:class:`EscapeCriterion`, named by ``escape_criterion``; the continuation runs
    the true plant when it is an equation (1) plant, else the model).  A run the true plant
    ended with a fault (``plant_fault``: its line, ``plant_fault_at``: the sample) counts as
    diverged and not converged; ``escaped`` is then about the state at the fault.
    ``arrays``: the per-sample values stay numpy arrays (``testbed report`` streams them out).
    ``replay``: what a recording's columns say happened (:func:`escaped_run`; None: the record's own).
    The reductions are :class:`RunTally`'s, here over the whole run as one chunk.
    """
    tally = RunTally(res.T)
    tally.add(0, res)
    return tally.summarize(sc, res, arrays=arrays, replay=replay, x_meas=res.x_meas is not None)


class MemStack:
    """A per-sample array made of chunks, in memory (``RunTally``'s default ``stack``): one chunk is itself."""

    def __init__(self) -> None:
        self.parts: list = []

    def append(self, a: npt.ArrayLike) -> None:
        self.parts.append(np.asarray(a))

    def result(self) -> np.ndarray:
        return self.parts[0] if len(self.parts) == 1 else np.concatenate(self.parts)


class RunTally:
    """:func:`summarize`'s reductions over a run's per-sample record, fed a chunk of samples at a time
    (``add``, in the order of the samples): counts, the first and last samples, the maximum norm, the
    agreement of the ends, the DoS intervals, the losses by cause, and the per-sample values kept by
    ``stack`` (default in memory; ``testbed.record.timingstats.Stack``: in a file, so that a run's summary is made in
    bounded memory).  A whole run is one chunk (``summarize``); any chunking gives the same summary."""

    #: per-sample keys of the summary and the ``SimResult`` field each comes from
    PER_SAMPLE = (("t", "t"), ("x", "x"), ("x_meas", "x_meas"), ("u", "u"), ("q", "q"), ("xi", "xi_enc"),
                  ("E", "E_enc"), ("E_dec", "E_dec"), ("theta", "theta"), ("symbols", "symbols"))
    #: the last samples kept (``loop_state_from_samples`` reads the last two)
    TAIL = ("theta", "symbols", "q", "xi_dec", "E_dec", "xi_enc", "E_enc")

    def __init__(self, T: float, stack: Callable[[], Any] = MemStack) -> None:
        self.T = float(T)
        self.stack = stack
        self.per_sample = {key: stack() for key, _ in self.PER_SAMPLE}
        self.saturated_at, self.withheld_at, self.breaks = stack(), stack(), stack()
        self.samples = self.saturations = self.lost = 0
        self.x_max = None           # max |x_k| so far (NaN once a NaN was seen, as np.max gives)
        self.agree = True
        self.withheld: bool | None = None    # None: the record has no withheld
        self.causes: np.ndarray | None = None  # counts of each loss cause (None: the record has no loss_cause)
        # the first and last sample of each run of the attacker's drops (16 bytes a run, not a tuple of two ints)
        self.run_first, self.run_last = array("q"), array("q")
        self._open: int | None = None
        self._last_on = False
        self.tail: dict = {}

    def add(self, k0: int, res: SimResult) -> None:
        """Samples k0 .. k0 + len(res.theta) - 1 of the run (``res``: their per-sample arrays; its
        ``lockstep_breaks`` the run's sample numbers in them)."""
        n = len(res.theta)
        for key, name in self.PER_SAMPLE:
            v = res.u if key == "u" and res.u_plant is None else res.u_plant if key == "u" else getattr(res, name)
            if v is not None:
                self.per_sample[key].append(v)
        sat = np.asarray(res.saturated)
        self.saturations += int(sat.sum())
        self.saturated_at.append(np.nonzero(sat)[0] + k0)
        if res.withheld is not None:
            self.withheld = True
            self.withheld_at.append(np.nonzero(res.withheld)[0] + k0)
        self.breaks.append(np.asarray(list(res.lockstep_breaks), dtype=np.int64))
        known = np.isfinite(res.E_enc)
        self.agree = self.agree and not len(res.lockstep_breaks) and not (res.withheld is None and not known.all()) \
            and equal_where(res.xi_enc, res.xi_dec, known) and equal_where(res.E_enc, res.E_dec, known)
        self.lost += int(np.asarray(res.theta).sum())
        if len(res.x):
            m = np.max(np.abs(res.x))
            self.x_max = m if self.x_max is None else np.maximum(self.x_max, m)
        if res.loss_cause is not None:
            c = np.bincount(np.asarray(res.loss_cause, dtype=np.int64), minlength=len(LOSS_KINDS) + 1)
            self.causes = c if self.causes is None else _add_counts(self.causes, c)
        on = np.asarray(res.theta if res.loss_cause is None else np.asarray(res.loss_cause) == ATTACKER, dtype=bool)
        if n:  # the runs of the attacker's drops (``SimResult.intervals``), carried over the chunks
            prev = np.concatenate(([self._last_on], on[:-1]))
            ons = (np.flatnonzero(on & ~prev) + k0).tolist()
            offs = (np.flatnonzero(~on & prev) + k0).tolist()
            if self._open is not None and offs:
                self.run_first.append(self._open)
                self.run_last.append(offs.pop(0) - 1)
                self._open = None
            self.run_first.extend(ons[:len(offs)])
            self.run_last.extend(b - 1 for b in offs)
            if len(ons) > len(offs):
                self._open = ons[-1]
            self._last_on = bool(on[-1])
            for name in self.TAIL:
                v = np.asarray(getattr(res, name))[-2:]
                old = self.tail.get(name)
                self.tail[name] = v if old is None else np.concatenate([old, v])[-2:]
        self.samples += n

    def interval_pairs(self) -> np.ndarray:
        """The realized DoS schedule's ``(a_i, tau_i)`` as an (n, 2) array, in order (the runs of the attacker's
        drops, disjoint and in k order: ``SimResult.intervals``, without a Python object per interval)."""
        a = np.frombuffer(self.run_first, dtype=np.int64)
        b = np.frombuffer(self.run_last, dtype=np.int64)
        if self._open is not None:
            a, b = np.append(a, self._open), np.append(b, self.samples - 1)
        return np.column_stack((a * self.T, (b - a) * self.T))

    def summarize(self, sc: Scenario, res: SimResult, *, arrays: bool = False, replay: Replay | None = None,
                  record: Callable[[], Iterable[tuple[int, np.ndarray, Replay]]] | None = None,
                  x_meas: bool = False) -> dict:
        """:func:`summarize`'s document from the chunks added: ``res`` gives the run's scalars (x_final, flow
        status, faults, K, simulator); ``record`` the record again, ``record() -> iter((k0, X, replay))``, for a
        method's ends (:func:`escaped_run`; default ``res`` whole); ``x_meas``: the key ``x_meas`` is written
        (a sensor read x_k)."""
        L = (lambda a: a) if arrays else (lambda a: a.tolist())
        P = {key: st.result() for key, st in self.per_sample.items() if key != "x_meas" or x_meas}
        model = sc.make_model()
        tol = sc.run.converge_tol
        flow_diverged = res.flow_status != FLOW_OK
        diverged = flow_diverged or res.plant_fault is not None or res.method_fault is not None
        crit = EscapeCriterion.for_loop(model, sc.quantizer, tol)
        chunked = None
        if record is None:
            last = res
        else:  # the last two samples (what the paper's end state reads) and the run's scalars
            last = SimResult(T=res.T, t=res.t, x=res.x, u=res.u, q=self.tail.get("q", res.q), q_enc=res.q_enc,
                             xi_enc=self.tail.get("xi_enc", res.xi_enc), E_enc=self.tail.get("E_enc", res.E_enc),
                             xi_dec=self.tail.get("xi_dec", res.xi_dec), E_dec=self.tail.get("E_dec", res.E_dec),
                             theta=self.tail.get("theta", res.theta), symbols=self.tail.get("symbols", res.symbols),
                             saturated=res.saturated, x_final=res.x_final, flow_status=res.flow_status, K=res.K,
                             method_fault=res.method_fault)
            chunked = (self.samples, record)
        # a recording's plant or method whose stored code was not run (no --trust-code): not judged
        escaped = None if sc.code_not_run() else escaped_run(sc, last, crit, replay, record=chunked)
        cb = sc.make_method().codebook(model.n, sc.quantizer)
        o = run_outcome(sc, None, res.x_final, None, bits=cb.bits, saturations=self.saturations, agree=self.agree,
                        diverged=diverged, escaped=escaped, plant_fault=res.plant_fault, method_fault=res.method_fault,
                        losses=None if self.causes is None else loss_counts_of(self.causes),  # channel.loss_cause
                        x_max=self.x_max, lost=self.lost)
        breaks = self.breaks.result()
        withheld_at = None if self.withheld is None else self.withheld_at.result()
        return json_clean({
            "scenario": sc.name,
            **plant_and_model(sc),
            "method": o["method"],
            "method_params": dict(sc.method.params),
            "n": model.n,
            "m": model.m,
            "T": sc.T,
            "M": sc.quantizer.M,
            "Lambda": sc.quantizer.Lambda,
            "mode": sc.quantizer.mode,
            "bits": o["bits"],
            "K": res.K.tolist(),
            "t": L(P["t"]),
            "x": L(P["x"]),
            **({"x_meas": L(P["x_meas"])} if x_meas else {}),  # what the sensor read ([plant.sensor])
            "u": L(P["u"]),  # what acted (after [plant.actuator], as recorded)
            "q": L(P["q"]),
            "xi": L(P["xi"]),
            "E": L(P["E"]),
            "E_dec": L(P["E_dec"]),
            "theta": P["theta"] if arrays else np.asarray(P["theta"][:]).astype(int).tolist(),
            "symbols": L(P["symbols"]),
            "saturations": o["saturations"],
            "saturated_at": L(self.saturated_at.result()),
            "dos_intervals": self.interval_pairs().tolist(),  # = SimResult.intervals().to_list() (test_simulate.py)
            "packets_dropped": o["packets_dropped"],
            "encoder_decoder_agree": o["encoder_decoder_agree"],
            "x_final": o["x_final"],
            "final_norm": o["final_norm"],
            "converged": o["converged"],
            "escaped": o["escaped"],
            "escape_criterion": crit.to_dict(),
            "diverged": o["diverged"],
            "diverged_at": (res.method_fault_at if res.method_fault is not None else
                            res.diverged_at if res.plant_fault is None else res.plant_fault_at),
            "plant_fault": o["plant_fault"],
            "plant_fault_at": res.plant_fault_at,
            "method_fault": o["method_fault"],
            "method_fault_at": res.method_fault_at,
            "lockstep_breaks": breaks.tolist() if isinstance(breaks, np.ndarray) else breaks,
            "max_norm": o["max_norm"],
            "samples_lost": o["samples_lost"],
            "timing_mode": sc.run.timing,
            "simulator": res.simulator,
            "rule": sc.quantizer.rule,
            "withheld_at": [] if self.withheld is None else
            withheld_at.tolist() if isinstance(withheld_at, np.ndarray) else withheld_at,
            "losses": o["losses"],
        })


def _add_counts(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    n = max(len(a), len(b))
    return np.pad(a, (0, n - len(a))) + np.pad(b, (0, n - len(b)))


def run_outcome(sc: Scenario, x: np.ndarray | None, x_final: np.ndarray, theta: npt.ArrayLike | None, *, bits: int,
                saturations: int, agree: bool, diverged: bool, escaped: bool | None, plant_fault: str | None = None,
                method_fault: str | None = None, losses: dict | None = None, x_max: float | None = None,
                lost: int | None = None) -> dict:
    """How a run ended, as ``testbed simulate --json`` states it (:func:`summarize`) and a campaign's row
    of a batch-kernel run (``testbed.campaign.batch``): method, bits, converged (not diverged and
    max |x_final| < converge_tol), escaped, diverged, final_norm, max_norm, x_final, saturations,
    samples_lost = packets_dropped (theta's lost samples), losses by cause, encoder_decoder_agree, the faults.
    ``x`` and ``theta`` None: ``x_max`` and ``lost`` instead (``RunTally``'s, tallied over the run's chunks)."""
    final_norm = float(np.max(np.abs(x_final)))
    if x is not None:  # else ``x_max`` (max |x_k|, None: no samples) and ``lost`` (sum of theta), tallied
        x_max = np.max(np.abs(x)) if len(x) else None
        lost = int(np.asarray(theta).sum())
    return {"method": sc.method.name, "bits": bits, "converged": bool(not diverged and final_norm < sc.run.converge_tol),
            "escaped": None if escaped is None else bool(escaped), "diverged": bool(diverged), "final_norm": final_norm,
            "max_norm": float(max(0.0 if x_max is None else x_max, final_norm)), "x_final": x_final.tolist(),
            "saturations": int(saturations), "samples_lost": lost, "packets_dropped": lost, "losses": losses,
            "encoder_decoder_agree": agree, "plant_fault": plant_fault, "method_fault": method_fault}
