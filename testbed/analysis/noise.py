"""The paper's quantizer under a noisy sensor: how large ``[quantizer] E_min`` must be, and the ball
the state then converges to (docs/plants-and-quantizer.md, "The quantizer under sensor noise").

Model.  The sensor reads y_k = x_k + v_k with ||v_k||_inf <= b (``[plant.sensor]``: b =
``SensorSpec.bound()``), the state takes a disturbance ||w_k||_inf <= w.  The encoder quantizes
y_k in Q(xi_k, E_k); q_k is the centre of y_k's cell, ||y_k - q_k||_inf <= E_k / M (4), so
||x_k - q_k||_inf <= b + E_k / M.  Both the plant and the prediction (xi) apply u_k = K q_k:

    x_k+1 - xi_k+1 = phi_T(x_k, u_k) - phi_T(q_k, u_k) + w_k,
    ||x_k+1 - xi_k+1|| <= Lambda (b + E_k / M) + w          (Lambda = e^{L T}, the Lipschitz bound)

and y_k+1 lies in Q(xi_k+1, E_k+1) when Lambda (b + E_k / M) + w + b <= E_k+1.  Once E_k sits at
the floor (E_k = E_k+1 = E_min, rule (E) with theta = 0 shrinks E by Lambda / M < 1 onto it):

    E_min >= ((1 + Lambda) b + w) / (1 - Lambda / M)                          (the guarantee)

With the linearized flow's growth a = ||A~||_inf in place of Lambda (A~ = e^{A T}, the Jacobian
of phi_T at the equilibrium) the same argument gives the estimate that matters near the origin.
Below it the measured state leaves the box again and again: a saturation, the OVERFLOW codeword,
both ends zoom out, and the loop recaptures the state (``resilient`` mode) -- the regime the
paper's theory does not cover.  Above it, with e_k = x_k - q_k bounded by b + E_min / M, the
linearized closed loop x_k+1 = A_cl x_k - B~ K e_k + w_k (A_cl = A~ + B~ K) keeps x in the ball

    ||x||_inf <= sum_j ||A_cl^j B~ K||_inf (b + E_min / M) + sum_j ||A_cl^j||_inf w     (the ball)

The other side: every lost sample multiplies E by Lambda (rule (E)), so after a DoS burst of
l samples the box is E_min Lambda^l wide; too large an E_min turns a burst into an error the
loop cannot recover from (the paper's example escapes with E_min = 4e-4, see the sweep).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..control import c2d, closed_loop
from ..device import DeviceSpec, SensorSpec
from ..simbatch import simulate_scenario


def e_min_guarantee(b: float, Lambda: float, M: int, w: float = 0.0) -> float:
    """((1 + Lambda) b + w) / (1 - Lambda / M): the E_min that keeps every measured state in its box
    (worst case over the Lipschitz bound Lambda; inf when M <= Lambda)."""
    return np.inf if M <= Lambda else ((1.0 + Lambda) * b + w) / (1.0 - Lambda / M)


def growth(model, T: float) -> float:
    """a = ||e^{A T}||_inf: how much the linearized flow over one period stretches an error."""
    Ad, _ = c2d(model.A, model.B, T)
    return float(np.max(np.sum(np.abs(Ad), axis=1)))


def e_min_estimate(model, T: float, M: int, b: float, w: float = 0.0) -> float:
    """The guarantee with the linearized growth ``growth(model, T)`` in place of Lambda."""
    return e_min_guarantee(b, growth(model, T), M, w)


def ball_radius(model, K, T: float, M: int, b: float, E_min: float, w: float = 0.0, terms: int = 2000) -> float:
    """The ultimate bound of ||x||_inf of the linearized loop with ||x_k - q_k|| <= b + E_min / M
    and a disturbance ||w_k|| <= w (the sums of the module docstring, ``terms`` terms)."""
    Ad, Bd = c2d(model.A, model.B, T)
    Acl = closed_loop(Ad, Bd, K)
    BK = Bd @ np.asarray(K, dtype=float).reshape(Bd.shape[1], Ad.shape[0])
    P = np.eye(Ad.shape[0])
    s_e = s_w = 0.0
    for _ in range(terms):
        s_e += float(np.max(np.sum(np.abs(P @ BK), axis=1)))
        s_w += float(np.max(np.sum(np.abs(P), axis=1)))
        P = Acl @ P
    return s_e * (b + E_min / M) + s_w * w


def with_sensor(sc, sensor: SensorSpec, E_min: float):
    """Scenario ``sc`` with ``[plant.sensor]`` = ``sensor`` and ``[quantizer] E_min`` = ``E_min``."""
    dev = sc.plant.device or DeviceSpec()
    plant = dataclasses.replace(sc.plant, device=dataclasses.replace(dev, sensor=sensor))
    return dataclasses.replace(sc, plant=plant, quantizer=dataclasses.replace(sc.quantizer, E_min=float(E_min)))


def sweep(sc, scales, E_mins, *, distribution: str = "uniform", seed: int = 1, settle: float | None = None) -> list[dict]:
    """Simulate ``sc`` (per-sample loop) for every sensor noise ``scale`` and ``E_min``: one row each.

    ``settle``: the time [s] after which saturations count as the steady regime (default: half
    the run).  Row: scale, E_min, the sensor's bound b, saturations (all, after ``settle``),
    ``tail_norm`` (max ||x||_inf after ``settle``), ``final_norm``, ``ball`` (the predicted radius).
    """
    model = sc.make_model()
    N = sc.n_steps
    k0 = int(N // 2 if settle is None else round(settle / sc.T))
    rows = []
    for s in scales:
        sensor = SensorSpec(distribution=distribution, scale=float(s), seed=seed)
        b = sensor.bound()
        for e in E_mins:
            res = simulate_scenario(with_sensor(sc, sensor, e))
            tail = res.x[k0:] if len(res.x) > k0 else res.x[-1:]
            rows.append({"scale": float(s), "E_min": float(e), "b": b, "saturations": int(res.saturations),
                         "saturations_after": int(res.saturated[k0:].sum()),
                         "tail_norm": float(np.max(np.abs(tail))), "final_norm": res.final_norm,
                         "ball": ball_radius(model, sc.K, sc.T, sc.quantizer.M, b, e)})
    return rows


__all__ = ["e_min_guarantee", "e_min_estimate", "growth", "ball_radius", "with_sensor", "sweep"]
