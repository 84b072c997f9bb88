"""``testbed vectors``: every vector checked against an independent computation.

phi_T against scipy's ``solve_ivp`` at tight tolerance (to 1e-9; an independent integrator, so not
bit for bit), with f written out here from docs/plants-and-quantizer.md; the symbols, q_k and u_k
against Algorithm 1, the box centre and control law (2) computed again here in plain Python; the
acks against Algorithm 2's last_rx; the payloads against the documented byte layouts."""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from testbed import cli, scenario


def _lienard(a, b):
    def f(t, x, u):
        return [x[1] + x[0] + a * x[0] ** 3 - b * x[0] ** 5, -x[0] + u[0]]
    return f


def _pendulum(g, l, mass, c):
    def f(t, x, u):
        return [x[1], (g / l) * math.sin(x[0]) - c / (mass * l * l) * x[1] + u[0] / (mass * l * l)]
    return f


RHS = {"paper": _lienard(1.0 / 3.0, 1.0 / 50.0), "pendulum": _pendulum(9.81, 1.0, 1.0, 0.1)}


def _vectors(capsys, name, n):
    assert cli.main(["vectors", name, "--n", str(n), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def _phi(f, x, u, T):
    sol = solve_ivp(f, (0.0, T), x, args=(u,), method="DOP853", rtol=1e-13, atol=1e-15)
    assert sol.success
    return sol.y[:, -1]


def _index(x, xi, E, M):
    """Algorithm 1 again: the cell of each coordinate in Q(xi, E), and whether x is outside."""
    idx, sat = 0, False
    for j in reversed(range(len(x))):
        d = x[j] - xi[j]
        sat |= abs(d) > E
        c = min(M - 1, max(0, int(math.floor((d + E) / (2 * E) * M))))
        idx = idx * M + c
    return idx, sat


@pytest.mark.parametrize("name", ["paper", "pendulum"])
def test_the_flow_map_vectors_agree_with_solve_ivp(capsys, name):
    out = _vectors(capsys, name, 6)
    sc = scenario.load(name)
    assert out["T"] == sc.T and out["n"] == 2 and out["m"] == 1
    assert len(out["flow_map"]) == 6
    assert out["flow_map"][0]["x"] == [float(v) for v in sc.x0] and out["flow_map"][0]["u"] == [0.0]
    for v in out["flow_map"]:
        assert v["status"] == 0
        ref = _phi(RHS[name], v["x"], v["u"], out["T"])
        assert np.max(np.abs(np.asarray(v["x_T"]) - ref)) <= 1e-9 * max(1.0, float(np.max(np.abs(ref)))), v


def test_the_loop_vectors_follow_the_algorithms_and_the_byte_layouts(capsys):
    out = _vectors(capsys, "paper", 1)
    sc = scenario.load("paper")
    K = np.asarray(sc.K)
    M = sc.quantizer.M
    loop = out["loop"]
    assert [r["k"] for r in loop] == list(range(len(loop))) and len(loop) >= 5
    assert loop[0]["plant"]["x"] == [float(v) for v in sc.x0]
    last_rx = -1
    for r in loop:
        k, e, c, p = r["k"], r["encoder"], r["controller"], r["plant"]
        assert r["sensor"]["x"] == p["x"]  # no sensor model in paper
        assert bytes.fromhex(r["sensor"]["payload"]) == struct.pack("<2d", *p["x"])
        idx, sat = _index(p["x"], e["xi"], e["E"], M)
        assert (e["symbol"], e["saturated"]) == (idx, sat)
        assert bytes.fromhex(e["payload"]) == idx.to_bytes(1, "big")
        dropped = k in out["loop_dropped"]
        assert r["attacker"]["forwarded"] is not dropped
        assert (c["xi"], c["E"]) == (e["xi"], e["E"])  # encoder and decoder in lockstep
        if dropped:
            assert (c["theta"], c["symbol"], c["u"]) == (1, -1, [0.0])
        else:
            last_rx = k
            q = [e["xi"][j] - e["E"] + (2 * ((idx // M ** j) % M) + 1) * e["E"] / M for j in range(2)]
            assert c["q"] == q == e["q"]
            assert (c["theta"], c["symbol"]) == (0, idx)
            assert c["u"] == [float(K[0, 0] * q[0] + K[0, 1] * q[1])]
        assert c["last_rx"] == last_rx
        assert bytes.fromhex(c["payload"]) == struct.pack("<Bi", c["theta"], last_rx) + struct.pack("<d", *c["u"])
        assert r["encoder_ack"]["result"] == "resolved"
        assert p["u_acted"] == c["u"] and p["flow_status"] == 0
        assert np.max(np.abs(np.asarray(p["x_next"]) - _phi(RHS["paper"], p["x"], p["u_acted"], out["T"]))) <= 1e-9
    for a, b in zip(loop, loop[1:]):
        assert b["plant"]["x"] == a["plant"]["x_next"]


def test_a_bad_scenario_is_one_line_and_exit_2(capsys):
    assert cli.main(["vectors", "no-such-scenario", "--json"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "no-such-scenario" in err
