"""The rules of thumb a scenario can break and still run: one warning line each, printed on stderr by
``testbed run`` and ``testbed simulate`` before the run (docs/plants-and-quantizer.md, "The quantizer
under sensor noise").

The sensor reads y_k = x_k + v_k with ||v_k||_inf <= b (``SensorSpec.bound``) and the state takes a
disturbance ||w_k||_inf <= w.  The box Q(xi_k, E_k) must hold y_k, not only x_k:

* **E_min against the noise.** At the floor E_k = E_min the next reading stays in its box when
  E_min >= ((1 + a) b + w) / (1 - a / M); with the Lipschitz bound a = Lambda = e^(L T) that is the
  guarantee, with the linearized flow's growth a = ||e^(A T)||_inf the estimate near the origin.  A
  floor below the estimate is the regime of repeated saturations: ``e_min_warning``.
* **E0 against x0.** The first box is Q(0, E0) and the first reading is x0 + v_0: it can fall outside
  unless E0 >= ||x0||_inf + b (Assumption 5, ||x0||_inf <= E0, with the sensor's noise added):
  ``e0_warning``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..loop.control import c2d

if TYPE_CHECKING:
    from plants.base import Plant

    from ..loop.device import DisturbanceSpec
    from .spec import Scenario


def e_min_guarantee(b: float, Lambda: float, M: int, w: float = 0.0) -> float:
    """((1 + Lambda) b + w) / (1 - Lambda / M): the E_min that keeps every measured state in its box
    (worst case over the Lipschitz bound Lambda; inf when M <= Lambda)."""
    return np.inf if M <= Lambda else ((1.0 + Lambda) * b + w) / (1.0 - Lambda / M)


def growth(model: Plant, T: float) -> float:
    """a = ||e^{A T}||_inf: how much the linearized flow over one period stretches an error."""
    Ad, _ = c2d(model.A, model.B, T)
    return float(np.max(np.sum(np.abs(Ad), axis=1)))


def disturbance_bound(spec: DisturbanceSpec | None) -> float:
    """A bound on ||w_k||_inf of ``[plant.disturbance]`` (``DisturbanceSpec``; 0 without one): the
    constant's largest entry plus the noise's (the uniform half-width, 4 sigma for normal noise)."""
    if spec is None:
        return 0.0
    c = max((abs(float(v)) for v in spec.constant), default=0.0)
    return c + (spec.scale if spec.distribution == "uniform" else 4.0 * spec.scale)


def e_min_warning(E_min: float, b: float, w: float, a: float, M: int) -> str | None:
    """The warning when ``[quantizer] E_min`` is below the estimate ((1 + a) b + w) / (1 - a / M) of the
    noise's need (b: the sensor's bound, w: the disturbance's, a: the linearized growth), else None."""
    if not (b > 0 or w > 0):
        return None
    need = e_min_guarantee(b, a, M, w)
    if E_min >= need:
        return None
    return (f"[quantizer] E_min = {E_min:g} is below what the sensor's noise needs, E_min >= ((1 + a) b + w) / "
            f"(1 - a/M) = {need:.3g} (b = {b:.3g}, w = {w:.3g}, a = ||e^(A T)||_inf = {a:.4g}, M = {M}; "
            "docs/plants-and-quantizer.md): expect the measured state to leave its box again and again")


def e0_warning(E0: float, x0_norm: float, b: float) -> str | None:
    """The warning when the first reading x0 + v_0 can fall outside the first box Q(0, E0), that is
    ||x0||_inf + b > E0 with a noisy sensor (b > 0), else None."""
    if not b > 0 or x0_norm + b <= E0:
        return None
    return (f"[quantizer] E0 = {E0:g} leaves no room for the sensor's noise at x0: ||x0||_inf + b = {x0_norm:g} + "
            f"{b:.3g} > E0, so the first reading can fall outside the first box Q(0, E0) (give E0 >= "
            f"{x0_norm + b:.6g}; docs/plants-and-quantizer.md)")


def warnings(sc: Scenario) -> list[str]:
    """The rule-of-thumb warnings of scenario ``sc`` (a ``Scenario``), each one line; empty when none.

    A rule applies when the method uses the key it is about (``Method.uses``: E_min, E0) and, for E0, when
    the scenario does not ask for x0 outside the first box (``allow_x0_outside``)."""
    from .. import methods

    dev = sc.plant.device
    b = dev.sensor.bound() if dev is not None and dev.sensor is not None else 0.0
    w = disturbance_bound(dev.disturbance if dev is not None else None)
    if not (b > 0 or w > 0):
        return []
    uses = set(methods.resolve(sc.method.name, sc.method.base_dir or None).uses)
    qp = sc.quantizer
    out = []
    if "E_min" in uses:
        out.append(e_min_warning(qp.E_min, b, w, growth(sc.make_model(), sc.T), qp.M))
    if "E0" in uses and not _allow_x0_outside(sc):
        out.append(e0_warning(qp.E0, float(np.max(np.abs(sc.x0))), b))
    return [line for line in out if line]


def _allow_x0_outside(sc: Scenario) -> bool:
    """``[quantizer] allow_x0_outside = true`` in the scenario's text."""
    import tomllib

    try:
        return bool(sc.document().get("quantizer", {}).get("allow_x0_outside", False))
    except (tomllib.TOMLDecodeError, AttributeError):
        return False


__all__ = ["disturbance_bound", "e0_warning", "e_min_guarantee", "e_min_warning", "growth", "warnings"]
