"""Foxglove: the well-known schemas in every recording, decoded by protobuf and by Foxglove's own stack.

* the shipped descriptor sets are foxglove-sdk's, and the layout file is current;
* ``/phase`` (one ``foxglove.SceneUpdate`` a sample) and ``/log`` (``foxglove.Log``) decode with the
  protobuf classes of their descriptor sets and say what the run did;
* slow: npm ``@mcap/core`` + ``protobufjs`` decode a recording with zero errors (skipped without npm,
  failed instead where the capability ``npm`` is required: ``failclosed.require``);
* process: ``testbed run --foxglove PORT`` serves the run over Foxglove's WebSocket protocol.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import socket
import struct
import subprocess
import threading
import time
from pathlib import Path

import helpers.sims
import numpy as np
import pytest
from failclosed import import_or_require, require

from testbed import scenario
from testbed.record import schema
from testbed.view import foxglove as fx

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def sim_recording(tmp_path_factory):
    """The paper's 8 s simulation recorded: (sc, res, path)."""
    return helpers.sims.sim_recording(tmp_path_factory.mktemp("fox"), duration=8.0)


def _messages(path, topic):
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        for sch, _ch, m in make_reader(f).iter_messages(topics=[topic]):
            yield sch, m


def test_shipped_schemas_are_foxglove_sdks():
    fm = import_or_require("foxglove.messages", "foxglove")
    for name in ("Log", "SceneUpdate"):
        s = getattr(fm, name).get_schema()
        assert fx.descriptor_set(s.name) == s.data, f"regenerate: python tools/gen_foxglove_schemas.py ({name})"


def test_the_layout_file_is_current():
    import_or_require("foxglove.layouts", "foxglove")
    doc = ROOT / "docs" / "foxglove-layout.json"
    assert doc.read_text() == fx.layout_json(), "regenerate: python -m testbed.view.foxglove > " \
                                                "docs/foxglove-layout.json"


def test_phase_plane_scene_updates(sim_recording):
    sc, res, path = sim_recording
    msgs = list(_messages(path, fx.TOPIC_PHASE))
    assert len(msgs) == len(res.t)
    cls = schema.classes_from(msgs[0][0].data)["foxglove.SceneUpdate"]
    for k in (0, 17, len(res.t) - 1):
        u = cls.FromString(msgs[k][1].data)
        ents = {e.id: e for e in u.entities}
        assert set(ents) == {"trajectory", "recent", "state"} and all(e.frame_id == fx.FRAME for e in u.entities)
        assert not ents["recent"].lines             # T = 0.1 s: every update has the whole trajectory
        t_ns = ents["state"].timestamp.seconds * 10**9 + ents["state"].timestamp.nanos
        assert t_ns == msgs[0][1].log_time + k * 100_000_000          # t_k = t0 + k T
        traj = ents["trajectory"].lines[0]
        assert traj.scale_invariant and traj.thickness > 0
        assert (traj.points[-1].x, traj.points[-1].y) == tuple(res.x[k])   # the strip ends at x_k
        box = ents["state"].lines[0]
        assert box.scale_invariant and box.type == 1                        # LINE_LOOP
        xi, E = res.xi_enc[k], res.E_enc[k]
        corners = {(p.x, p.y) for p in box.points}
        assert corners == {(xi[0] - E, xi[1] - E), (xi[0] + E, xi[1] - E), (xi[0] + E, xi[1] + E),
                           (xi[0] - E, xi[1] + E)}
        assert [(s.pose.position.x, s.pose.position.y) for s in ents["state"].spheres] == [tuple(res.x[k]),
                                                                                            tuple(xi)]
    (roa,) = list(_messages(path, fx.TOPIC_ROA))
    assert cls.FromString(roa[1].data).entities[0].id == "roa"


def test_fast_runs_send_the_trajectory_every_50_ms_and_what_is_new_between():
    cls = schema.classes_from(fx.descriptor_set(fx.SCENE))[fx.SCENE]
    ps = fx.PhaseScene(window=1.0, refresh=10)
    x = np.stack([np.cos(np.arange(100) / 10.0), np.sin(np.arange(100) / 10.0)], axis=1)
    for k in range(100):
        ents = {e.id: e for e in cls.FromString(ps.sample(k, x[k])).entities}
        if k % 10 == 0:
            assert (ents["trajectory"].lines[0].points[-1].x, ents["trajectory"].lines[0].points[-1].y) == \
                tuple(x[k]) and not ents["recent"].lines
            start = tuple(x[k])
        else:
            pts = [(p.x, p.y) for p in ents["recent"].lines[0].points]
            assert "trajectory" not in ents and pts[0] == start and pts[-1] == tuple(x[k]) and len(pts) <= 11


@pytest.mark.slow  # half a second or more on a warm cache
def test_trajectory_stays_small_at_any_rate():
    sc = scenario.load("paper")
    ps = fx.PhaseScene(window=1.0)
    rng = np.random.default_rng(0)
    x = np.cumsum(rng.normal(scale=0.02, size=(20_000, 2)), axis=0)
    sizes = [len(ps.sample(k, x[k])) for k in range(0, 20_000)]
    assert len(ps.kept) <= fx.MAX_POINTS and ps.eps > 1.0 / 400   # it had to coarsen
    assert max(sizes) < (fx.MAX_POINTS + fx.TAIL + 8) * 24 + 500, max(sizes)
    assert sc  # the scenario is only the window's source in a run


def test_log_panel_messages(sim_recording):
    sc, res, path = sim_recording
    msgs = list(_messages(path, fx.TOPIC_LOG))
    cls = schema.classes_from(msgs[0][0].data)["foxglove.Log"]
    logs = [cls.FromString(m.data) for _, m in msgs]
    text = [lg.message for lg in logs]
    assert text[0].startswith("run sim-paper") and text[-1].startswith("run ended")
    assert sum("DoS attack starts" in t for t in text) == 2 and sum("DoS attack ends" in t for t in text) == 2
    assert sum(t.startswith("saturation") for t in text) == int(res.saturated.sum())
    assert logs[1].level == fx.WARNING and logs[0].timestamp.seconds > 1_600_000_000


def test_telemetry_header_stamp_and_log10_E(sim_recording):
    sc, res, path = sim_recording
    msgs = list(_messages(path, "/telemetry/encoder"))
    cls = schema.classes()["EncoderSample"]
    t0 = msgs[0][1].log_time
    for k in (0, 30):
        m = cls.FromString(msgs[k][1].data)
        assert m.header.stamp.seconds * 10**9 + m.header.stamp.nanos == t0 + k * 100_000_000
        assert m.log10_E == pytest.approx(np.log10(res.E_enc[k]), abs=0)


# ---------------------------------------------------------------------------- Foxglove's own stack (npm)
def _npm_modules() -> Path:
    if not shutil.which("npm") or not shutil.which("node"):
        require("npm", "npm/node not installed: cannot run @mcap/core + protobufjs")
    cache = Path(os.environ.get("TESTBED_NPM_CACHE", Path.home() / ".cache" / "testbed-npm"))
    mods = cache / "node_modules"
    if not all((mods / p).exists() for p in ("@mcap/core", "protobufjs", "fzstd")):
        cache.mkdir(parents=True, exist_ok=True)
        r = subprocess.run(["npm", "install", "--prefix", str(cache), "--no-audit", "--no-fund", "--silent",
                            "@mcap/core@2", "protobufjs@7", "fzstd@0.1"], capture_output=True, text=True,
                           timeout=300)
        if r.returncode:
            require("npm", f"npm install of @mcap/core, protobufjs, fzstd failed: {r.stderr.strip()[-300:]}")
    return mods


@pytest.mark.slow
def test_foxgloves_decoding_stack_reads_every_message(sim_recording):
    sc, res, path = sim_recording
    mods = _npm_modules()
    r = subprocess.run(["node", str(ROOT / "tests" / "data" / "js" / "decode_mcap.js"), str(path)], capture_output=True,
                       text=True, timeout=120, env=dict(os.environ, NODE_PATH=str(mods)))
    assert r.returncode == 0, r.stderr[-2000:]
    d = json.loads(r.stdout)
    assert d["errors"] == 0, d["first_error"]
    assert d["schemas"]["/log"] == "foxglove.Log" and d["schemas"]["/phase"] == "foxglove.SceneUpdate"
    assert d["topics"]["/phase"] == len(res.t) and d["topics"]["/log"] >= 4
    ent = d["samples"]["/phase"]["entities"][0]
    assert ent.get("frameId", ent.get("frame_id")) == fx.FRAME   # protobufjs camel-cases unless keepCase
    assert d["samples"]["/telemetry/plant"]["header"]["stamp"]["seconds"] > 1_600_000_000


# ---------------------------------------------------------------------------- live: testbed run --foxglove
class WsClient:
    """The client side of Foxglove's WebSocket protocol, enough to subscribe and receive (RFC 6455 frames)."""

    def __init__(self, port: int, timeout: float):
        end = time.monotonic() + timeout
        while True:
            try:
                self.s = socket.create_connection(("127.0.0.1", port), timeout=5)
                break
            except OSError:
                if time.monotonic() > end:
                    raise
                time.sleep(0.1)
        key = base64.b64encode(os.urandom(16)).decode()
        self.s.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                        f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                        f"Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.s.recv(1)
        assert b" 101 " in head.split(b"\r\n")[0], head
        self.s.settimeout(timeout)   # the run's nodes take seconds to start: no message meanwhile
        self.buf = b""

    def _read(self, n: int) -> bytes:
        while len(self.buf) < n:
            chunk = self.s.recv(65536)
            if not chunk:
                raise ConnectionError("closed")
            self.buf += chunk
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def recv(self):
        b0, b1 = self._read(2)
        n = b1 & 0x7F
        if n == 126:
            (n,) = struct.unpack(">H", self._read(2))
        elif n == 127:
            (n,) = struct.unpack(">Q", self._read(8))
        return b0 & 0x0F, self._read(n)

    def send_text(self, text: str) -> None:
        data = text.encode()
        mask = os.urandom(4)
        head = bytes([0x81]) + (bytes([0x80 | len(data)]) if len(data) < 126 else
                                bytes([0x80 | 126]) + struct.pack(">H", len(data)))
        self.s.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))


@pytest.mark.process
def test_run_foxglove_serves_the_run_live(tmp_path):
    import_or_require("foxglove", "foxglove")
    from helpers.cli import tb_cmd

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    # 8 s: the nodes start at once, so a viewer that connects and subscribes while the run is already
    # going (on a loaded machine, seconds late) still sees every topic
    p = subprocess.Popen(tb_cmd("run", "paper", "--duration", "8", "--json", "--no-record", "--foxglove", str(port),
                                "--foxglove-linger", "1"),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    got: dict[str, list] = {}
    errors: list = []

    refused: list = []   # channels the server did not know yet when we subscribed

    def client():
        try:
            c = WsClient(port, 120)
            subs, channels, next_id = {}, {}, 1

            def subscribe(ch):
                nonlocal next_id
                subs[next_id] = ch
                c.send_text(json.dumps({"op": "subscribe", "subscriptions": [{"id": next_id, "channelId": ch["id"]}]}))
                next_id += 1

            end = time.monotonic() + 120
            while time.monotonic() < end:
                op, data = c.recv()
                if op == 1:
                    m = json.loads(data)
                    if m.get("op") == "advertise":
                        for ch in m["channels"]:
                            channels[ch["id"]] = ch
                            subscribe(ch)
                    elif m.get("op") == "status" and m.get("message", "").startswith("Unknown channel ID: "):
                        # foxglove-sdk sends an advertisement before it records the channel as
                        # advertised; a subscription that came in between is refused: subscribe again
                        cid = int(m["message"].rsplit(":", 1)[1])
                        refused.append(cid)
                        if cid in channels and refused.count(cid) <= 20:
                            time.sleep(0.01)
                            subscribe(channels[cid])
                elif op == 2 and data[0] == 1:
                    sid, _t = struct.unpack_from("<IQ", data, 1)
                    ch = subs[sid]
                    got.setdefault(ch["topic"], []).append((ch, data[13:]))
                elif op == 8:
                    return
        except (ConnectionError, OSError) as e:
            errors.append(e)

    th = threading.Thread(target=client, daemon=True)
    th.start()
    try:
        out, err = p.communicate(timeout=180)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, 9)
            p.wait()
    th.join(10)
    assert p.returncode == 0, err[-2000:]
    s = json.loads(out)
    assert s["foxglove"]["url"] == f"ws://127.0.0.1:{port}" and s["foxglove"]["errors"] == 0
    assert {"/telemetry/plant", "/phase", "/log"} <= set(got), (set(got), errors, refused)
    ch, data = got["/phase"][-1]
    assert ch["schemaName"] == "foxglove.SceneUpdate"
    fds = base64.b64decode(ch["schema"])
    u = schema.classes_from(fds)["foxglove.SceneUpdate"].FromString(data)
    assert {"recent", "state"} <= {e.id for e in u.entities}
    ch, data = got["/telemetry/plant"][0]
    m = schema.classes_from(base64.b64decode(ch["schema"]))["testbed.PlantSample"].FromString(data)
    assert len(m.x) == 2 and m.header.stamp.seconds > 1_600_000_000
    assert len(got["/phase"]) >= 30


def test_the_outline_is_computed_off_the_writers_thread_and_not_at_fast_rates():
    """A recorder's writer thread must never wait for the outline's grid (a minute at T = 1 ms)."""
    from testbed.wire import messages as msg

    fast = scenario.with_overrides(scenario.load("paper"), {"T": 0.001})
    assert not fx.FoxgloveTopics(fast, background=True).roa_wanted
    tap = fx.FoxgloveTopics(scenario.load("paper"), background=True)
    start = msg.Start(run_id="r", t0_ns=10**18, T_ns=10**8, n_steps=300, digest="", timing="ideal",
                      ack_via_attacker=False)
    items = tap.start(start, 10**18) + tap.flush(10**18)   # flush waits for the background thread
    assert [(t, lt) for t, _n, _d, lt in items if t == fx.TOPIC_ROA] == [(fx.TOPIC_ROA, 10**18)] and tap.roa_sent
