"""Test vectors a node implemented elsewhere can check offline (``testbed vectors SCENARIO --json``).

Two parts, both computed by the functions the bundled nodes run:

- ``flow_map``: (x, u) -> phi_T(x, u) and its status for N points (``testbed.loop.flow.phi_T``, the
  plant node's and the ends' flow map), x and u drawn from a fixed seed around the scenario's
  region (and its x0, u = 0 first);
- ``loop``: a short run of the scenario's loop in ideal timing by the nodes' state machines
  (``PlantProtocol`` on the scenario's true plant, ``EncoderProtocol``, ``ControllerProtocol``),
  every sample's messages as each role reads and writes them (numbers and the payload bytes).
  The attacker forwards every symbol except those of ``DROPPED`` (so the vectors show a lost
  sample: the controller's loss-deadline decision, theta = 1, and the encoder's replay); the
  scenario's own attack schedule is not applied.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from . import messages as msg

if TYPE_CHECKING:

    from ..scenario import Scenario

#: samples of the short loop whose symbol the attacker drops
DROPPED = (3,)
LOOP_SAMPLES = 8


def _f(v: Any) -> list[float]:
    return [float(a) for a in np.asarray(v, dtype=np.float64).ravel()]


def flow_vectors(sc: Scenario, n: int, seed: int = 0) -> list[dict]:
    """``n`` points (x, u) -> phi_T(x, u) of the scenario's plant model (the first: x0, u = 0)."""
    from ..loop.flow import phi_T

    model = sc.make_model()
    rng = np.random.default_rng(seed)
    r = max(float(np.max(np.abs(sc.x0))), float(sc.quantizer.E0), 1e-3)
    K = np.asarray(sc.K, dtype=np.float64)
    X = rng.uniform(-2.0 * r, 2.0 * r, size=(n, model.n))
    U = X @ K.T + rng.uniform(-r, r, size=(n, model.m))
    if n:
        X[0] = np.asarray(sc.x0, dtype=np.float64)
        U[0] = 0.0
    if n > 2:  # one far point: many steps, rejections
        X[-1] *= 20.0
        U[-1] *= 20.0
    XT, st = phi_T(model, X, U, sc.T, sc.flow)
    return [{"x": _f(X[i]), "u": _f(U[i]), "x_T": _f(XT[i]), "status": int(st[i])} for i in range(n)]


def loop_vectors(sc: Scenario, samples: int = LOOP_SAMPLES) -> list[dict]:
    """The first ``samples`` samples of the loop, ideal timing, by the nodes' state machines."""
    from ..loop.protocol import ControllerProtocol, EncoderProtocol, PlantProtocol, Send

    model = sc.make_model()
    method = sc.make_method()
    enc = method.make_encoder(model, sc.K, sc.quantizer, sc.flow)
    dec = method.make_decoder(model, sc.K, sc.quantizer, sc.flow)
    N = min(int(samples), int(sc.n_steps))
    ep, cp = EncoderProtocol(enc, sc.n_steps), ControllerProtocol(dec, sc.n_steps)
    proc = sc.make_process()
    proc.reset(np.array(sc.x0, dtype=np.float64))
    pp = PlantProtocol.for_scenario(sc, proc)
    out = []
    try:
        for k in range(N):
            x = np.array(proc.x, dtype=np.float64)
            xm = pp.measure(k, x)
            rec: dict = {"k": k, "plant": {"x": _f(x)},
                         "sensor": {"x": _f(xm), "payload": msg.Sensor(k, 0, tuple(_f(xm))).encode()[0].hex()}}
            send = ep.sensor(k, xm)
            if isinstance(send, Send):
                data = enc.codebook.pack(send.symbol)
                rec["encoder"] = {"xi": _f(send.xi), "E": float(send.E), "symbol": int(send.symbol),
                                  "saturated": bool(send.saturated), "q": _f(send.q), "payload": bytes(data).hex()}
                forwarded = k not in DROPPED
                rec["attacker"] = {"forwarded": forwarded}
                decisions = cp.symbol(k, data) if forwarded else [cp.deadline(k)]
            else:
                rec["encoder"] = {"withheld": True}
                rec["attacker"] = {"forwarded": False}
                decisions = [cp.deadline(k)]
            (d,) = decisions
            assert d is not None  # sample k is the next: decided by its symbol or its deadline
            u = _f(d.u)
            act = msg.Actuation(k, 0, d.theta, tuple(u), d.last_rx).encode()[0]
            rec["controller"] = {"symbol": int(d.symbol), "xi": _f(d.xi), "E": float(d.E), "q": _f(d.q),
                                 "theta": int(d.theta), "last_rx": int(d.last_rx), "reason": int(d.reason),
                                 "u": u, "payload": act.hex()}
            rec["encoder_ack"] = {"theta": int(d.theta), "last_rx": int(d.last_rx),
                                  "result": ep.ack(k, d.theta, d.last_rx)}
            ua, _ = pp.check_input(d.u)
            st = pp.step(ua)
            rec["plant"].update({"u_acted": _f(pp.u_applied), "x_next": _f(proc.x), "flow_status": int(st)})
            out.append(rec)
            if st != 0:
                break
    finally:
        proc.close()
    return out


def vectors(sc: Scenario, n: int = 8) -> dict:
    """Everything ``testbed vectors`` prints (see the module docstring)."""
    model = sc.make_model()
    fo = sc.flow
    return {"scenario": sc.name, "n": int(model.n), "m": int(model.m), "T": float(sc.T), "T_ns": int(round(sc.T * 1e9)),
            "flow": {"rtol": fo.rtol, "atol": fo.atol, "x_max": fo.x_max, "max_steps": int(fo.max_steps)},
            "flow_map": flow_vectors(sc, n), "loop_dropped": list(DROPPED), "loop": loop_vectors(sc)}
