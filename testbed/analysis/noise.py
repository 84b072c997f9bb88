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
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..loop.control import c2d, closed_loop
from ..loop.device import DeviceSpec, SensorSpec
from ..scenario.rulesofthumb import e_min_guarantee, growth  # the one definition (the warnings of run/simulate)
from ..sim.trajectory import simulate_scenario

if TYPE_CHECKING:
    from plants.base import Plant

    from ..scenario import Scenario
    from .parallel import Progress


def e_min_estimate(model: Plant, T: float, M: int, b: float, w: float = 0.0) -> float:
    """The guarantee with the linearized growth ``growth(model, T)`` in place of Lambda."""
    return e_min_guarantee(b, growth(model, T), M, w)


def ball_radius(model: Plant, K: np.ndarray, T: float, M: int, b: float, E_min: float, w: float = 0.0,
                terms: int = 2000) -> float:
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


def with_sensor(sc: Scenario, sensor: SensorSpec, E_min: float) -> Scenario:
    """Scenario ``sc`` with ``[plant.sensor]`` = ``sensor`` and ``[quantizer] E_min`` = ``E_min``."""
    dev = sc.plant.device or DeviceSpec()
    plant = dataclasses.replace(sc.plant, device=dataclasses.replace(dev, sensor=sensor))
    return dataclasses.replace(sc, plant=plant, quantizer=dataclasses.replace(sc.quantizer, E_min=float(E_min)))


def sweep(sc: Scenario, scales: Sequence[float], ratios: Sequence[float], *, distribution: str = "uniform",
          seed: int = 1, settle: float | None = None, progress: Progress | None = None) -> dict:
    """Simulate ``sc`` (the per-sample loop) with sensor noise of every ``scale`` and E_min = ratio * b
    for every ``ratio`` (b = the noise's bound, ``SensorSpec.bound``).

    ``settle``: the time [s] from which saturations and ||x|| count as the steady regime (default
    three quarters of the run).  Per scale: b, the E_min guarantee and the linearized estimate;
    per run: ``saturations`` (all, and ``saturations_after`` settle: OVERFLOW recaptures),
    ``tail_norm`` (max ||x||_inf after settle), ``ball`` (the predicted radius at that E_min),
    ``inside_ball``, ``final_norm`` and ``escaped`` (the state ends farther from the origin than
    x0 started: a DoS burst's zoom-out the loop did not recover from; ``testbed simulate``'s escape
    criterion asks for ||x|| below ``converge_tol``, which a noisy loop need not reach).
    """
    model = sc.make_model()
    qp = sc.quantizer
    N = sc.n_steps
    settle = 0.75 * N * sc.T if settle is None else float(settle)
    k0 = min(max(int(round(settle / sc.T)), 0), max(N - 1, 0))
    x0 = float(np.max(np.abs(sc.x0)))
    a = growth(model, sc.T)
    out: dict[str, Any] = {"scenario": sc.name, "distribution": distribution, "seed": int(seed), "M": qp.M,
                           "Lambda": qp.Lambda, "growth": a, "settle_s": k0 * sc.T, "samples": N, "scales": []}
    done, total = 0, len(scales) * len(ratios)
    for s in scales:
        sensor = SensorSpec(distribution=distribution, scale=float(s), seed=int(seed))
        b = sensor.bound()
        entry: dict[str, Any] = {"scale": float(s), "b": b, "E_min_guarantee": e_min_guarantee(b, qp.Lambda, qp.M),
                 "E_min_estimate": e_min_guarantee(b, a, qp.M), "runs": []}
        for r in ratios:
            e = float(r) * b
            scn = with_sensor(sc, sensor, e)
            res = simulate_scenario(scn)
            tail = float(np.max(np.abs(res.x[k0:]))) if len(res.x) > k0 else float("nan")
            ball = ball_radius(model, sc.K, sc.T, qp.M, b, e)
            entry["runs"].append({"ratio": float(r), "E_min": e, "saturations": int(res.saturations),
                                  "saturations_after": int(res.saturated[k0:].sum()), "tail_norm": tail,
                                  "ball": ball, "inside_ball": bool(tail <= ball), "final_norm": res.final_norm,
                                  "escaped": bool(not res.final_norm <= x0)})
            done += 1
            if progress is not None:
                progress(done, total)
        out["scales"].append(entry)
    return out


def plot_sweep(data: dict, path: str | Path, *, size: str = "page", title: str = "") -> Path:
    """Two panels over E_min / b: the OVERFLOW recaptures after the transient, and the state's
    steady size against the predicted ball; the estimate and the guarantee marked per scale."""
    from ..common import figstyle

    plt = figstyle.pyplot()
    with figstyle.style(size):
        fig, axs = figstyle.subplots(size, 2, 1, aspect=0.4, sharex=True)
        ax1, ax2 = axs[:, 0]
        markers = ("o", "s", "^", "D", "v")
        for i, entry in enumerate(data["scales"]):
            col = figstyle.CYCLE[i % len(figstyle.CYCLE)]
            mk = markers[i % len(markers)]
            ms = 6.5 - 1.5 * (i % 3)  # overlapping curves (the relation scales with b) stay visible
            runs = [r for r in entry["runs"] if r["ratio"] > 0]
            x = np.array([r["ratio"] for r in runs])
            lab = f"{data['distribution']} noise, scale {entry['scale']:g}"
            ax1.plot(x, [r["saturations_after"] for r in runs], "-", marker=mk, ms=ms, color=col, label=lab)
            ok = np.array([not r["escaped"] for r in runs], dtype=bool)
            tail = np.array([r["tail_norm"] for r in runs])
            ax2.plot(x[ok], tail[ok], "-", marker=mk, ms=ms, color=col)
            ax2.plot(x[~ok], tail[~ok], "x", color=col, markersize=8)
            ax2.plot(x, [r["ball"] for r in runs], ":", color=col)
        g = data["scales"][0]  # the ratios do not depend on the scale (b cancels)
        for ax in (ax1, ax2):
            ax.axvline(g["E_min_estimate"] / g["b"], color="0.3", lw=0.8, ls="--")
            ax.axvline(g["E_min_guarantee"] / g["b"], color="0.3", lw=0.8, ls="-.")
        ax1.set_xscale("log")
        ax1.set_ylabel(f"saturations after {data['settle_s']:g} s")
        ax1.set_title(title or f"{data['scenario']}: E_min against the sensor noise", fontsize="medium")
        ax2.set_yscale("log")
        ax2.set_xlabel("E_min / b  (b: the noise's bound)")
        ax2.set_ylabel(r"max $\|x\|_\infty$ after settling")
        from matplotlib.lines import Line2D

        extra = [Line2D([], [], color="0.3", ls="--", label="linearized estimate"),
                 Line2D([], [], color="0.3", ls="-.", label="guarantee (Lambda)"),
                 Line2D([], [], color="0.3", ls=":", label="predicted ball"),
                 Line2D([], [], color="0.3", marker="x", ls="", label="escaped")]
        h, _ = ax1.get_legend_handles_labels()
        figstyle.legend_below(fig, h + extra, ncol=2, axes=ax2)
        out = figstyle.save(fig, path)
        plt.close(fig)
    return out


__all__ = ["e_min_guarantee", "e_min_estimate", "growth", "ball_radius", "with_sensor", "sweep", "plot_sweep"]
