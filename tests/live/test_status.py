"""The live status line (``testbed.live.status``), fast: its text, and its counts over telemetry records as a
collector holds them (each record counted once however often it ticks; the losses by cause those that
``recorded_losses``, the summary's function, gives over the whole run)."""

from __future__ import annotations

import io

import numpy as np

from testbed.live.status import LiveStatus, status_text
from testbed.loop.channel import recorded_losses
from testbed.wire import messages as msg


class Records:
    """Telemetry records by role and k, queried as the launcher's collector is (``last_k``, ``record``)."""

    def __init__(self):
        self.d = {r: {} for r in ("plant", "encoder", "attacker", "controller")}
        self.summaries = {}

    def last_k(self, role):
        return max(self.d[role], default=-1)

    def record(self, role, k):
        return self.d[role].get(k)

    def snapshot_summaries(self):
        return self.summaries


def test_status_text():
    losses = {"attacker": 3, "channel": 1, "late": 0, "withheld": 2}
    assert status_text(28, 40, losses, 10, 0.679, 6.79e-4) == \
        ("sample 28/40 | lost 6 (attacker 3, channel 1, network 0, late 0, withheld 2) | deadline misses 10 | "
         "E_k enc 0.679, dec 0.000679")
    assert status_text(0, 40, dict.fromkeys(losses, 0), 0, None, None).endswith("E_k enc -, dec -")


def test_the_counts_are_those_of_the_run_and_each_record_is_read_once():
    rng = np.random.default_rng(3)
    N, T = 200, 0.01
    dropped = rng.random(N) < 0.2
    silent = (rng.random(N) < 0.1) & ~dropped
    other = (rng.random(N) < 0.05) & ~dropped & ~silent                  # lost on the way (channel)
    reason = np.where(rng.random(N) < 0.03, msg.ControllerTelemetry.INVALID, msg.ControllerTelemetry.DEADLINE)
    theta = dropped | silent | other
    miss = rng.random(N) < 0.1
    col, out = Records(), io.StringIO()
    st = LiveStatus(N, T, out, tty=False)
    for k in range(N):
        col.d["plant"][k] = msg.PlantTelemetry(k=k, t_ns=k, sensor_tx_ns=k, u_rx_ns=k, delay_ns=0, theta=int(theta[k]),
                                               flags=msg.PlantTelemetry.FLAG_MISS if miss[k] else 0, flow_status=0,
                                               x=(0.0, 0.0), u=(0.0,))
        col.d["encoder"][k] = msg.EncoderTelemetry(k=k, sensor_tx_ns=k, rx_ns=k, tx_ns=k, symbol=0, saturated=0,
                                                   silent=int(silent[k]), E=float(k), xi=(0.0, 0.0), q=(0.0, 0.0))
        col.d["attacker"][k] = msg.AttackerTelemetry(k=k, rx_ns=k, tx_ns=k, dropped=int(dropped[k]), corrupted=0,
                                                     attack_on=int(dropped[k]), dropped_total=0, forwarded_total=0)
        col.d["controller"][k] = msg.ControllerTelemetry(
            k=k, sym_stamp_ns=k, rx_ns=k, tx_ns=k, symbol=0, theta=int(theta[k]),
            reason=int(reason[k]) if theta[k] else msg.ControllerTelemetry.RECEIVED, E=float(k) / 2, xi=(0.0, 0.0),
            q=(0.0, 0.0), u=(0.0,))
        if k % 7 == 0:
            st.tick(col, now=float(k))   # every 7th sample, and twice at the same k: nothing counted twice
            st.tick(col, now=float(k) + 1.5)
    col.summaries = {"controller": {"late": 4}}   # 4 symbols came after their sample was decided: late
    st.close(col)
    lines = out.getvalue().splitlines()
    assert len(lines) > 20 and "\r" not in out.getvalue()
    want = recorded_losses(theta, withheld=silent, attacker=dropped,
                           invalid=theta & (reason == msg.ControllerTelemetry.INVALID),
                           superseded=np.zeros(N, dtype=bool), late_symbols=4)
    assert want["late"] == 4 and want["network"] > 0  # no channel model: a sent sample never received is the network's
    assert lines[-1] == status_text(N, N, want, int(miss.sum()), float(N - 1), (N - 1) / 2)
    assert sum(want.values()) == int(theta.sum())


def test_the_console_loss_line_adds_up(tmp_path, capsys):
    """``testbed simulate``'s text names every lost sample under its one cause (``losses``), the channel's too,
    and the causes add up to the samples lost (the issue's '34 dropped in 8 DoS intervals' counted the channel's
    drops as the attacker's)."""
    import json
    import re
    from pathlib import Path

    from testbed import cli
    from testbed.loop.channel import loss_text

    assert loss_text({"attacker": 3, "channel": 1, "late": 0, "withheld": 2}) == \
        "attacker 3, channel 1, network 0, late 0, withheld 2"
    paper = (Path(__file__).resolve().parents[2] / "testbed" / "scenario" / "bundled" / "paper.toml").read_text()
    path = tmp_path / "net.toml"
    path.write_text(paper.replace("[run]", "[network]\nseed = 3\n[network.symbol]\nloss = 0.1\n\n[run]"))
    assert cli.main(["simulate", str(path), "--duration", "10", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["losses"]["channel"] > 0 and sum(s["losses"].values()) == s["packets_dropped"], s["losses"]
    assert cli.main(["simulate", str(path), "--duration", "10"]) == 0
    out = capsys.readouterr().out
    m = re.search(r"(\d+) samples, (\d+) lost \((attacker \d+, channel \d+, network \d+, late \d+, withheld \d+)\)", out)
    assert m and int(m.group(2)) == s["packets_dropped"] and m.group(3) == loss_text(s["losses"]), out
