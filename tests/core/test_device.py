"""A plant that is a device ([plant.sensor], [plant.actuator], [plant.disturbance]): the device model
against independent computations, the simulator under a noisy sensor against the E_min relation and
the ball of testbed.analysis.noise, and the recording's x_meas."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.cli import tb_here

from testbed import scenario
from testbed.analysis import noise
from testbed.loop.device import ActuatorSpec, DeviceSpec, DisturbanceSpec, SensorSpec
from testbed.loop.protocol import OdeProcess
from testbed.record.columns import read_columns
from testbed.scenario.spec import ScenarioError
from testbed.sim.trajectory import kernel_refusal, simulate_scenario

PAPER = scenario.load("paper").source


def noisy_paper(extra: str, *, E0: float = 0.12, duration: float = 30.0, E_min: float | None = None) -> str:
    """The paper's example with a device section; E0 = 0.12 keeps x0 = (0.1, 0.1) inside the first box
    by more than the noise (the paper's x0 sits on the corner of Q(0, 0.1))."""
    text = PAPER.replace("E0 = 0.1\n", f"E0 = {E0}\n" + ("" if E_min is None else f"E_min = {E_min}\n"))
    text = text.replace("duration = 30.0", f"duration = {duration}")
    return text + "\n" + extra


def _stream(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, stream]))


# ============================================================================ the device model
def test_sensor_reading_is_noise_then_adc_seeded_and_prefix_stable():
    spec = DeviceSpec(sensor=SensorSpec(distribution="uniform", scale=1e-3, seed=11, resolution=1e-4))
    x = np.array([0.123456, -0.0654321])
    long = spec.make(2, 1, 0.1)
    ys = [long.measure(k, x) for k in range(50)]
    short = spec.make(2, 1, 0.1)
    assert all(np.array_equal(short.measure(k, x), ys[k]) for k in range(10))  # prefix-stable
    rng = _stream(11, 1)  # an independent reading of the documented formula
    for k in range(50):
        v = 1e-3 * (2.0 * rng.random(2) - 1.0)
        want = 1e-4 * np.round((x + v) / 1e-4)
        assert np.array_equal(ys[k], want), k
        assert np.all(np.abs(ys[k] - x) <= 1e-3 + 0.5e-4 + 1e-15)
    normal = DeviceSpec(sensor=SensorSpec(scale=2e-3, seed=5)).make(2, 1, 0.1)
    rng = _stream(5, 1)
    assert np.array_equal(normal.measure(0, x), x + 2e-3 * rng.standard_normal(2))
    with pytest.raises(ValueError, match="out of order"):
        normal.measure(5, x)


def test_actuator_is_dac_then_saturation_then_rate_limit():
    T, sat, rate, step = 0.1, 0.5, 3.0, 0.01
    dev = DeviceSpec(actuator=ActuatorSpec(resolution=step, saturation=sat, rate=rate)).make(2, 1, T)
    rng = np.random.default_rng(0)
    prev = 0.0
    for _ in range(500):
        u = float(rng.normal(0.0, 1.0))
        got = float(dev.actuate(np.array([u]))[0])
        want = min(max(step * round(u / step), -sat), sat)  # Python's round: half to even, as numpy's
        want = prev + min(max(want - prev, -rate * T), rate * T)
        assert got == want
        assert abs(got) <= sat and abs(got - prev) <= rate * T + 1e-15
        prev = got
    assert dev.saturated > 0 and dev.rate_limited > 0


def test_simulated_plant_applies_actuator_and_disturbance_exactly():
    """x_k+1 = phi_T(x_k, actuator(u_k)) + w_k, re-integrated sample by sample by a separate OdeProcess."""
    text = noisy_paper("[plant.actuator]\nsaturation = 0.3\nrate = 2.0\n\n"
                       "[plant.disturbance]\nconstant = [1e-6, -2e-6]\nscale = 1e-6\nseed = 3\n", duration=6.0)
    sc = scenario.loads(text)
    assert isinstance(sc.plant.device.disturbance, DisturbanceSpec)
    res = simulate_scenario(sc)
    assert res.simulator == "per-sample"
    proc = OdeProcess(sc.make_plant(), sc.flow)
    rng = _stream(3, 2)
    prev = np.zeros(1)
    clipped = 0
    for k in range(len(res.t) - 1):
        u = np.clip(res.u[k], -0.3, 0.3)
        u = prev + np.clip(u - prev, -0.2, 0.2)
        clipped += int(not np.array_equal(u, res.u[k]))
        prev = u
        assert np.array_equal(res.u_plant[k], u), k
        proc.reset(res.x[k])
        proc.advance(u, sc.T)
        want = proc.x + (np.array([1e-6, -2e-6]) + 1e-6 * rng.standard_normal(2))
        assert np.array_equal(res.x[k + 1], want), k
    assert clipped > 0  # the limits did act
    c = res.counters["plant"]
    assert c["actuator_saturated"] > 0 and c["actuator_rate_limited"] > 0


# ============================================================================ E_min against the noise
def test_noisy_sensor_without_E_min_saturates_and_with_it_converges_to_the_ball():
    s = 1e-5
    sc = scenario.loads(noisy_paper(f"[plant.sensor]\ndistribution = \"uniform\"\nscale = {s}\nseed = 1\n",
                                    duration=45.0))
    model, q = sc.make_model(), sc.quantizer
    b = sc.plant.device.sensor.bound()
    est = noise.e_min_estimate(model, sc.T, q.M, b)
    guar = noise.e_min_guarantee(b, q.Lambda, q.M)
    assert b == s and est < guar
    k0 = int(35.0 / sc.T)
    # without E_min (and with it at the noise's bound): the measured state keeps leaving its box
    for e in (0.0, s):
        res = simulate_scenario(noise.with_sensor(sc, sc.plant.device.sensor, e))
        assert res.saturated[k0:].sum() >= 5, (e, np.flatnonzero(res.saturated))
        assert res.agree
    # at the linearized estimate (x 1.1) and at the guarantee: no saturation, and inside the ball
    for e in (1.1 * est, guar):
        res = simulate_scenario(noise.with_sensor(sc, sc.plant.device.sensor, e))
        assert res.saturations == 0, (e, np.flatnonzero(res.saturated))
        ball = noise.ball_radius(model, sc.K, sc.T, q.M, b, e)
        tail = float(np.max(np.abs(res.x[k0:])))
        assert tail <= ball, (e, tail, ball)
        assert res.agree


def test_ball_radius_bounds_the_worst_error_sequence_of_the_linear_loop():
    """The linearized loop x_k+1 = A_cl x_k - B K e_k driven, step by step, by the error sequence
    that maximizes entry i of x_N (e_j = -r sign of row i of A_cl^(N-1-j) B K): it stays inside
    ``ball_radius`` and comes close to it (the bound is a sum of norms, the worst case a norm of a sum)."""
    sc = scenario.load("paper")
    model = sc.make_model()
    from testbed.loop.control import c2d, closed_loop

    Ad, Bd = c2d(model.A, model.B, sc.T)
    Acl = closed_loop(Ad, Bd, sc.K)
    BK = Bd @ sc.K
    b, E_min, M, N = 1e-5, 1e-4, sc.quantizer.M, 400
    r = b + E_min / M
    ball = noise.ball_radius(model, sc.K, sc.T, M, b, E_min)
    powers = [np.eye(2)]
    for _ in range(N):
        powers.append(Acl @ powers[-1])
    worst = 0.0
    for i in range(2):
        x = np.zeros(2)
        for j in range(N):
            e = -r * np.sign((powers[N - 1 - j] @ BK)[i])
            x = Acl @ x - BK @ e
        worst = max(worst, abs(float(x[i])))
    assert worst <= ball and worst >= 0.5 * ball, (worst, ball)


# ============================================================================ simulator choice, recording, bad input
def test_batch_kernel_refuses_a_device_and_auto_runs_the_loop(tmp_path):
    text = noisy_paper("[plant.sensor]\nscale = 1e-6\nseed = 2\n", duration=3.0, E_min=3e-5)
    sc = scenario.loads(text)
    assert "device" in kernel_refusal(sc)
    f = tmp_path / "noisy.toml"
    f.write_text(text)
    rc, out, err = tb_here("simulate", f)
    assert rc == 0 and "simulator: the per-sample loop (the plant is a device: [plant.sensor])" in out, (out, err)
    rc, out, err = tb_here("simulate", f, "--simulator", "batch")
    assert rc == 2 and "device" in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.slow  # half a second or more on a warm cache
def test_recording_keeps_true_and_measured_state_and_resimulates(tmp_path):
    text = noisy_paper("[plant.sensor]\ndistribution = \"normal\"\nscale = 1e-6\nseed = 9\nresolution = 1e-6\n",
                       duration=4.0, E_min=3e-5)
    f = tmp_path / "noisy.toml"
    f.write_text(text)
    rec = tmp_path / "n.mcap"
    rc, out, err = tb_here("simulate", f, "--json", "--out", rec)
    assert rc in (0, 1), err
    sim = json.loads(out)
    res = simulate_scenario(scenario.loads(text))
    assert sim["x_meas"] == res.x_meas.tolist() and sim["x"] == res.x.tolist()
    assert not np.array_equal(res.x_meas, res.x)
    cols = read_columns(rec)
    assert np.array_equal(cols.get("plant", "x_meas")[:len(res.t)], res.x_meas)
    assert np.array_equal(cols.get("plant", "x")[:len(res.t)], res.x)
    rc, out, err = tb_here("report", rec, "--json")
    assert rc in (0, 1), err
    assert json.loads(out)["x_meas"] == sim["x_meas"]
    import testbed

    run = testbed.open(rec)
    assert np.array_equal(run.arrays["x_meas"], res.x_meas) and "x_meas2" in run.columns()
    rc, out, err = tb_here("resimulate", rec, "--json")
    r = json.loads(out)
    assert r["reproduced"] and r["max_state_error"] == 0, r


def test_no_device_sends_no_x_meas():
    sc = scenario.load("paper")
    assert sc.plant.device is None
    res = simulate_scenario(sc, n_steps=5, simulator="per-sample")
    assert res.x_meas is None


@pytest.mark.parametrize("extra, key", [
    ("[plant.sensor]\ndistribution = \"cauchy\"\n", "plant.sensor.distribution"),
    ("[plant.sensor]\nscale = -1.0\n", "plant.sensor.scale"),
    ("[plant.sensor]\nsigma = 1.0\n", "plant.sensor"),
    ("[plant.actuator]\nsaturation = 0.0\n", "plant.actuator.saturation"),
    ("[plant.actuator]\nrate = nan\n", "plant.actuator.rate"),
    ("[plant.disturbance]\nconstant = [1.0]\n", "plant.disturbance.constant"),
    ("[plant.disturbance]\nseed = 1.5\n", "plant.disturbance.seed"),
])
def test_bad_device_tables_are_one_line(tmp_path, extra, key):
    text = noisy_paper(extra)
    with pytest.raises(ScenarioError, match=rf"\[{key}\]"):
        scenario.loads(text)
    f = tmp_path / "bad.toml"
    f.write_text(text)
    rc, out, err = tb_here("simulate", f)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and key in err, err


def test_noise_command_sweeps_and_says_what_it_found(tmp_path):
    rc, out, err = tb_here("noise", "docs/examples/paper-noisy.toml", "--scale", "1e-5", "--ratio", "0", "3", "--json")
    assert rc == 0, err
    d = json.loads(out)
    (e,) = d["scales"]
    assert e["b"] == 1e-5 and e["E_min_estimate"] < e["E_min_guarantee"]
    none, floor = e["runs"]
    assert none["E_min"] == 0 and none["saturations_after"] > 0
    assert floor["E_min"] == pytest.approx(3e-5, rel=1e-12)
    assert floor["saturations"] == 0 and floor["inside_ball"] and not floor["escaped"]
    rc, out, err = tb_here("noise", "docs/examples/paper-noisy.toml", "--settle", "99")
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "--settle" in err, err


def test_campaigns_run_a_device_on_the_per_sample_loop():
    from testbed.campaign.batch import batch_key

    text = noisy_paper("[plant.sensor]\nscale = 1e-6\n", E_min=3e-5)
    assert batch_key(scenario.loads(text), text, "") is None
    assert batch_key(scenario.load("paper"), PAPER, "") is not None


@pytest.mark.slow  # seconds of numerics: analyses of a noisy scenario
def test_the_analysis_says_what_of_the_scenario_it_leaves_out(tmp_path):
    """The analysis runs the paper's loop: a [network] channel and the device are named in one stderr line and in
    ``not_modelled`` of the JSON (the paper's own example: nothing left out, no line)."""
    f = tmp_path / "lossy-device.toml"
    f.write_text(noisy_paper("[plant.sensor]\nscale = 1e-4\n\n[plant.actuator]\nresolution = 0.01\n\n"
                             "[network]\nseed = 1\nsymbol = { loss = 0.2 }\n", duration=3.0))
    for cmd in (["analyze", f, "--json"], ["worst-attack", f, "--attacks", "1", "--workers", "1", "--no-progress",
                                           "--json"]):
        rc, out, err = tb_here(*cmd)
        assert rc == 0, err
        assert json.loads(out)["not_modelled"] == ["[network]", "[plant.sensor]", "[plant.actuator]"]
        (line,) = [ln for ln in err.splitlines() if "note:" in ln]
        assert line.startswith(f"testbed {cmd[0]}: note: the analysis runs the paper's loop") and \
            line.endswith("it leaves out this scenario's [network], [plant.sensor], [plant.actuator], which "
                          "testbed simulate and testbed run model")
    rc, out, err = tb_here("analyze", "paper", "--json")
    assert rc == 0 and json.loads(out)["not_modelled"] == [] and "note:" not in err
