"""Zenoh transport: session configuration and every key expression of a live run.

All key expressions live here, under one prefix per run, ``testbed/<run_id>/``:

==============================  =====================  ======================================
key (after the prefix)          publisher -> reader    message (``testbed.io.messages``)
==============================  =====================  ======================================
``loop/sensor``                 plant -> encoder       ``Sensor``     x_k (control path)
``loop/symbol/tx``              encoder -> attacker    ``Symbol``     packed symbol bits
``loop/symbol/rx``              attacker -> controller ``Symbol``     forwarded symbol
``loop/actuation``              controller -> plant    ``Actuation``  theta_k, u_k
``loop/ack/tx``                 controller -> encoder  ``Ack``        theta_k (ideal ack channel),
                                (or -> attacker)                      or into the attacker
``loop/ack/rx``                 attacker -> encoder    ``Ack``        ack routed through the attacker
``telemetry/<node>``            each node              ``PlantTelemetry`` ... per sample
``attacker/status``             attacker               ``AttackerStatus`` on every change
``events/<node>``               each node              ``Event``      faults, saturations, ...
``summary/<node>``              each node              ``NodeSummary`` once, at exit
``control/start``               plant (time master)    ``Start``      t0 and run identity
``control/stop``                plant or launcher      ``Stop``
``alive/<node>``                liveliness tokens      present while a node's session is open
``ready/<node>``                liveliness tokens      node warmed up and sees all its peers
==============================  =====================  ======================================

Nodes are Zenoh peers with multicast scouting off, so nothing else on the
network joins a run: they meet through explicit endpoints (one listener, the
others connect; gossip then links every pair directly).
"""

from __future__ import annotations

import json
import socket
from dataclasses import dataclass
from pathlib import Path

ROOT = "testbed"
ROLES = ("plant", "encoder", "attacker", "controller")
COLLECTOR = "collector"          # the launcher's liveliness name
DEFAULT_RUN_ID = "default"
DEFAULT_HUB = "tcp/127.0.0.1:7447"   # standalone nodes: the plant listens here, the others connect
LOOPBACK_ANY = "tcp/127.0.0.1:0"     # a peer's own listener for direct links (loopback only)


@dataclass(frozen=True)
class Keys:
    """The key expressions of one run (``Keys.for_run(run_id)``)."""

    run_id: str
    prefix: str

    @classmethod
    def for_run(cls, run_id: str = DEFAULT_RUN_ID) -> "Keys":
        if not run_id or any(c in run_id for c in "/*$?#"):
            raise ValueError(f"run id {run_id!r} must be a non-empty key chunk (no / * $ ? #)")
        return cls(run_id=run_id, prefix=f"{ROOT}/{run_id}")

    # ---- control path
    @property
    def sensor(self) -> str:
        return f"{self.prefix}/loop/sensor"

    @property
    def symbol_tx(self) -> str:
        return f"{self.prefix}/loop/symbol/tx"

    @property
    def symbol_rx(self) -> str:
        return f"{self.prefix}/loop/symbol/rx"

    @property
    def actuation(self) -> str:
        return f"{self.prefix}/loop/actuation"

    @property
    def ack_tx(self) -> str:
        return f"{self.prefix}/loop/ack/tx"

    @property
    def ack_rx(self) -> str:
        return f"{self.prefix}/loop/ack/rx"

    def ack_for_encoder(self, via_attacker: bool) -> str:
        return self.ack_rx if via_attacker else self.ack_tx

    # ---- telemetry and bookkeeping
    def telemetry(self, node: str) -> str:
        return f"{self.prefix}/telemetry/{node}"

    def events(self, node: str) -> str:
        return f"{self.prefix}/events/{node}"

    def summary(self, node: str) -> str:
        return f"{self.prefix}/summary/{node}"

    @property
    def attacker_status(self) -> str:
        return f"{self.prefix}/attacker/status"

    @property
    def start(self) -> str:
        return f"{self.prefix}/control/start"

    @property
    def stop(self) -> str:
        return f"{self.prefix}/control/stop"

    def alive(self, node: str = "*") -> str:
        return f"{self.prefix}/alive/{node}"

    def ready(self, node: str = "*") -> str:
        return f"{self.prefix}/ready/{node}"

    @property
    def all(self) -> str:
        return f"{self.prefix}/**"

    def table(self) -> list[tuple[str, str]]:
        """(name, key expression) for the README and ``testbed run --keys``."""
        rows = [("sensor", self.sensor), ("symbol_tx", self.symbol_tx), ("symbol_rx", self.symbol_rx),
                ("actuation", self.actuation), ("ack_tx", self.ack_tx), ("ack_rx", self.ack_rx)]
        rows += [(f"telemetry_{r}", self.telemetry(r)) for r in ROLES]
        rows += [("attacker_status", self.attacker_status), ("events", self.events("<node>")),
                 ("summary", self.summary("<node>")), ("start", self.start), ("stop", self.stop),
                 ("alive", self.alive("<node>")), ("ready", self.ready("<node>"))]
        return rows

    @staticmethod
    def node_of(key: str) -> str:
        """Last chunk of a key expression (the node name of telemetry/events/alive keys)."""
        return str(key).rsplit("/", 1)[-1]


def make_config(listen: list[str] | tuple[str, ...] = (), connect: list[str] | tuple[str, ...] = (),
                config_file: str | Path | None = None, multicast: bool = False):
    """A peer-mode ``zenoh.Config``: explicit endpoints, multicast scouting off.

    ``config_file`` (JSON5, e.g. with a ``transport/link/tls`` section) is read
    first; mode, scouting, ``listen`` and ``connect`` given here override it.
    With no ``listen`` endpoint the peer listens on loopback only (Zenoh's own
    default would be every interface).
    """
    import zenoh

    conf = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast)))
    file_listen = _json_or_none(conf, "listen/endpoints")
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    elif not file_listen:
        conf.insert_json5("listen/endpoints", json.dumps([LOOPBACK_ANY]))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return conf


def _json_or_none(conf, key):
    try:
        v = json.loads(conf.get_json(key))
    except Exception:  # noqa: BLE001 - absent key
        return None
    if isinstance(v, dict):  # per-mode defaults: {"router": [...], "peer": [...]} - not user-set
        return None
    return v


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free right now on ``host`` (for one run's listener)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def endpoint_host(ep: str) -> str:
    """``tcp/10.0.0.1:7447`` -> ``10.0.0.1``."""
    rest = ep.split("/", 1)[-1]
    return rest.rsplit(":", 1)[0].strip("[]")


# QoS of the control path and of telemetry (keyword arguments for declare_publisher)
def control_qos() -> dict:
    import zenoh

    return dict(congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.REAL_TIME,
                express=True)


def telemetry_qos() -> dict:
    import zenoh

    return dict(congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA_LOW)
