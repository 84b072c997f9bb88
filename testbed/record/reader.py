"""The reference reader of a recording: every message decoded into its dataclass, through the
protobuf classes of the file's own schemas (``read`` -> ``Recording``).  Slow and thorough: the tests
compare the columnar reader (``testbed.record.columns``) against it."""

from __future__ import annotations

import gc
import io
import json
import struct
from collections import Counter, defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..wire import messages as msg
from . import schema
from .mcapfile import (
    CHUNK_HEAD,
    MAGIC,
    MSG_HEAD,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_MESSAGE,
    OP_METADATA,
    OP_SCHEMA,
)
from .recorded import recorded_scenario
from .topics import TELEMETRY_TOPICS

if TYPE_CHECKING:
    from google.protobuf.message import Message

    from ..scenario import Scenario


# ============================================================================ reading
@dataclass
class Recording:
    """Everything in one recording, decoded (``read``)."""

    path: str
    truncated: bool = False
    read_error: str | None = None
    metadata: dict[str, dict] = field(default_factory=dict)
    start: msg.Start | None = None
    stops: list[msg.Stop] = field(default_factory=list)
    telemetry: dict[str, dict[int, Any]] = field(default_factory=lambda: {r: {} for r in TELEMETRY_TOPICS})
    plant_final: msg.PlantTelemetry | None = None
    events: list[msg.Event] = field(default_factory=list)
    status: list[msg.AttackerStatus] = field(default_factory=list)
    summaries: dict[str, dict] = field(default_factory=dict)
    liveliness: list[tuple[int, str, str, bool]] = field(default_factory=list)  # (log ns, node, token, present)
    loop: dict[str, list] = field(default_factory=lambda: defaultdict(list))
    malformed: list[dict] = field(default_factory=list)
    counts: Counter = field(default_factory=Counter)
    duplicates: int = 0
    last_log_time: int = 0
    plant_source: dict | None = None   # set by ``scenario()``: how the plant module was loaded
    model_source: dict | None = None   # ... and the [model]'s, when it is another class
    _resolved: bool = field(default=False, repr=False)

    @property
    def source(self) -> str:
        return self.metadata.get("testbed.run", {}).get("source", "?")

    @property
    def scenario_toml(self) -> str | None:
        return self.metadata.get("testbed.scenario", {}).get("toml")

    def scenario(self) -> Scenario:
        """The scenario the run used (``recorded_scenario``); sets ``plant_source``, ``model_source``."""
        sc, ps, ms = recorded_scenario(self.metadata, self.path, _cache=self)
        self.plant_source, self.model_source = ps, ms
        return sc


class _Truncated(Exception):
    pass


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "zstd":
        import zstandard

        return zstandard.decompress(data, size)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    if compression == "":
        return data
    raise ValueError(f"unsupported chunk compression {compression!r}")


def _body_record(cls, body: bytes):
    from mcap.data_stream import ReadDataStream

    return cls.read(ReadDataStream(io.BytesIO(body)))


_IN_CHUNK = (OP_MESSAGE, OP_SCHEMA, OP_CHANNEL)   # the records a chunk may hold


def _decode(op: int, buf: bytes, body: int, end: int):
    """A record whose body is ``buf[body:end]``: a Message as a plain ``(channel id, log time,
    data)`` tuple (the hot path: an ``mcap.records.Message`` costs a few us each), a Schema or
    Channel as the ``mcap`` record."""
    if op == OP_MESSAGE:
        ch, _seq, lt, _pt = MSG_HEAD.unpack_from(buf, body)
        return ch, lt, buf[body + MSG_HEAD.size:end]
    from mcap.records import Channel, Schema

    return _body_record(Schema if op == OP_SCHEMA else Channel, buf[body:end])


def _records(data: bytes):
    """The records of an MCAP file held in memory, in file order: ``(opcode, object)``.

    A plain loop over the byte layout (the MCAP spec's records), ~10x the
    ``mcap`` library's stream reader on small messages; message indexes and the
    summary section are skipped.  Raises ``_Truncated`` where a crash cut the file.
    """
    from mcap.records import Metadata

    n = len(data)
    off = len(MAGIC)
    unpack_q = struct.Struct("<Q").unpack_from
    unpack_i = struct.Struct("<I").unpack_from
    while off < n:
        if off + 9 > n:
            raise _Truncated(f"record header cut at byte {off}")
        op = data[off]
        (length,) = unpack_q(data, off + 1)
        body, end = off + 9, off + 9 + length
        if end > n:
            raise _Truncated(f"record (opcode {op:#x}) of {length} bytes cut at byte {n}")
        if op == OP_CHUNK:
            _s, _e, size, _crc = CHUNK_HEAD.unpack_from(data, body)
            p = body + CHUNK_HEAD.size
            (clen,) = unpack_i(data, p)
            compression = data[p + 4:p + 4 + clen].decode()
            p += 4 + clen
            (rlen,) = unpack_q(data, p)
            inner = _decompress(compression, data[p + 8:p + 8 + rlen], size)
            m, k = len(inner), 0
            while k < m:
                iop = inner[k]
                (ilen,) = unpack_q(inner, k + 1)
                ib, ie = k + 9, k + 9 + ilen
                if ie > m:
                    raise ValueError("corrupt chunk: a record runs past its end")
                if iop in _IN_CHUNK:
                    yield iop, _decode(iop, inner, ib, ie)
                k = ie
        elif op in _IN_CHUNK:
            yield op, _decode(op, data, body, end)
        elif op == OP_METADATA:
            yield op, _body_record(Metadata, data[body:end])
        elif op in (OP_FOOTER, OP_DATA_END):
            yield op, None
            if op == OP_FOOTER:
                return
        off = end


@contextmanager
def no_gc() -> Iterator[None]:
    """Cyclic GC off while millions of small acyclic objects are made (a third of a long read)."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def read(path: str | Path, *, loop: bool = True) -> Recording:
    """Decode a recording into dataclasses (the reference reader; ``testbed.record.columns`` is the fast one).

    A file cut short by a crash is read up to its last complete chunk.
    """
    with no_gc():
        return _read(Path(path), loop)


def _read(path: Path, loop: bool) -> Recording:
    rec = Recording(path=str(path))
    data = path.read_bytes()
    if not data.startswith(MAGIC):
        raise ValueError(f"{path}: not an MCAP file")
    schemas: dict[int, dict[str, type[Message]]] = {}
    schema_names: dict[int, str] = {}
    channels: dict[int, tuple[str, str, type[Message] | None]] = {}
    seen_footer = False
    it = _records(data)
    while True:
        try:
            op, r = next(it)
        except StopIteration:
            break
        except Exception as e:  # noqa: BLE001 - a truncated or corrupt tail: keep what came before
            rec.truncated = True
            rec.read_error = f"{type(e).__name__}: {e}"
            break
        if op == OP_MESSAGE:
            channel_id, log_time, payload = r
            ch = channels.get(channel_id)
            if ch is None:
                continue
            topic, name, cls = ch
            rec.counts[topic] += 1
            if log_time > rec.last_log_time:
                rec.last_log_time = log_time
            if cls is None or (not loop and topic.startswith("/loop/")):
                continue
            try:
                m = cls.FromString(payload)
            except Exception as e:  # noqa: BLE001 - protobuf DecodeError
                rec.malformed.append({"topic": topic, "error": str(e)})
                continue
            _dispatch(rec, topic, name, m, log_time)
        elif op == OP_SCHEMA:
            if r.encoding == "protobuf":
                try:
                    schemas[r.id] = {schema.full_name(k): v for k, v in schema.classes().items()} \
                        if r.data == schema.file_descriptor_set() else schema.classes_from(r.data)
                except Exception:  # noqa: BLE001 - an unreadable schema: its messages are counted only
                    schemas[r.id] = {}
            schema_names[r.id] = r.name
        elif op == OP_CHANNEL:
            full = schema_names.get(r.schema_id, "")
            channels[r.id] = (r.topic, full.rsplit(".", 1)[-1], schemas.get(r.schema_id, {}).get(full))
        elif op == OP_METADATA:
            rec.metadata[r.name] = dict(r.metadata)
        elif op == OP_FOOTER:
            seen_footer = True
    if not seen_footer:
        rec.truncated = True
    return rec


def _dispatch(rec: Recording, topic: str, name: str, m, log_time: int) -> None:
    if name in ("PlantSample", "EncoderSample", "ControllerSample", "AttackerSample"):
        role = topic.rsplit("/", 1)[-1]
        t = schema.from_pb(m, name)
        if name == "PlantSample" and t.flags & msg.PlantTelemetry.FLAG_FINAL:
            rec.plant_final = t
            return
        d = rec.telemetry.setdefault(role, {})
        if t.k in d:
            rec.duplicates += 1
        d[t.k] = t
    elif name == "Event":
        rec.events.append(schema.from_pb(m, name))
    elif name == "AttackerStatus":
        rec.status.append(schema.from_pb(m, name))
    elif name == "RunStart":
        if rec.start is None:
            rec.start = schema.from_pb(m, name)
    elif name == "RunStop":
        rec.stops.append(schema.from_pb(m, name))
    elif name == "NodeSummary":
        try:
            rec.summaries[m.node] = json.loads(m.json)
        except ValueError:
            rec.summaries[m.node] = {"unparsed": m.json}
    elif name == "Liveliness":
        rec.liveliness.append((log_time, m.node, m.token, m.present))
    elif name == "Malformed":
        rec.malformed.append({"topic": topic, "key": m.key, "error": m.error})
    elif topic.startswith("/loop/"):
        rec.loop[topic].append(schema.from_pb(m, name))
