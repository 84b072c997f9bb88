"""The topics of a recording and their schemas: one table that the writer, the recorder, both readers
and ``docs/recording-format.md`` use."""

from __future__ import annotations

from ..wire.transport import ROLES

PROFILE = "testbed"           # MCAP header profile


_U64_MAX = 2**64 - 1          # MCAP times are uint64 ns


FORMAT_VERSION = "1"          # bump when a topic or field changes meaning


#: every node role (``wire.transport.ROLES``) publishes telemetry: its topic, in the order of the readers' columns
TELEMETRY_TOPICS = {r: f"/telemetry/{r}" for r in ROLES}


TELEMETRY_SCHEMA = {"plant": "PlantSample", "encoder": "EncoderSample", "controller": "ControllerSample",
                    "attacker": "AttackerSample"}


LOOP_TOPICS = {"/loop/sensor": "Sensor", "/loop/symbol/tx": "Symbol", "/loop/symbol/rx": "Symbol",
               "/loop/actuation": "Actuation", "/loop/ack/tx": "Ack", "/loop/ack/rx": "Ack"}


FIXED_TOPICS = {"/attacker/status": "AttackerStatus", "/control/start": "RunStart", "/control/stop": "RunStop",
                "/liveliness": "Liveliness", "/recorder/malformed": "Malformed"}


def schema_for_topic(topic: str) -> str | None:
    """The schema name a topic carries (None: not a topic of a recording)."""
    for role, t in TELEMETRY_TOPICS.items():
        if topic == t:
            return TELEMETRY_SCHEMA[role]
    if topic in LOOP_TOPICS:
        return LOOP_TOPICS[topic]
    if topic in FIXED_TOPICS:
        return FIXED_TOPICS[topic]
    if topic.startswith("/events/"):
        return "Event"
    if topic.startswith("/summary/"):
        return "NodeSummary"
    from ..view.foxglove import TOPICS as FOXGLOVE

    return FOXGLOVE.get(topic)
