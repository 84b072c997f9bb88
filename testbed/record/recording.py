"""MCAP recordings of runs (live or simulated): the writer, the reference reader, one set of topics.

``read`` decodes every message into a dataclass (simple, slow: the reference
the tests hold the fast reader to); the commands and ``testbed.open`` use the
streaming columnar reader, ``testbed.record.columns``.

Topics are the run's Zenoh keys without the ``testbed/<run_id>`` prefix; every
channel is protobuf (``testbed.record.schema``):

=========================  ==========================  ===============================================
topic                      schema                      content
=========================  ==========================  ===============================================
``/telemetry/plant``       ``testbed.PlantSample``     x_k, u_k, theta_k as received, timing, flags;
                                                       the final state x_N has flag bit 3
``/telemetry/encoder``     ``testbed.EncoderSample``   symbol, xi_k, E_k, q_k, saturation (Algorithm 1)
``/telemetry/controller``  ``testbed.ControllerSample``  xi_k, E_k, theta_k, q_k, u_k (Algorithm 2)
``/telemetry/attacker``    ``testbed.AttackerSample``  dropped / forwarded, attack on, totals
``/loop/sensor``           ``testbed.Sensor``          control path as it crossed the network
``/loop/symbol/tx|rx``     ``testbed.Symbol``          (live runs; at T >= 10 ms by default,
``/loop/actuation``        ``testbed.Actuation``       see ``testbed run --record-loop``)
``/loop/ack/tx|rx``        ``testbed.Ack``
``/attacker/status``       ``testbed.AttackerStatus``  every switch of the attack
``/events/<node>``         ``testbed.Event``           saturations, faults, peers lost, node deaths
``/summary/<node>``        ``testbed.NodeSummary``     a node's counters and timing at exit
``/control/start|stop``    ``testbed.RunStart|RunStop``  t0 and the run's identity; stops
``/liveliness``            ``testbed.Liveliness``      nodes appearing and going away
``/recorder/malformed``    ``testbed.Malformed``       anything that did not decode, as received
``/log``                   ``foxglove.Log``            start, end, attacks on and off, saturations,
                                                       faults, every node event (Foxglove's Log panel)
``/phase``                 ``foxglove.SceneUpdate``    one a sample: the phase plane (trajectory so far,
                                                       x_k, xi_k, the box Q(xi_k, E_k)), Foxglove's 3D panel
``/phase/roa``             ``foxglove.SceneUpdate``    once: the nominal region of attraction (n = 2,
                                                       T >= 10 ms)
=========================  ==========================  ===============================================

Metadata records: ``testbed.scenario`` (name, TOML text, reference, folder, plant module source),
``testbed.software`` (versions), ``testbed.run`` (source live|simulate, run id,
host, command line, options), and at a clean close ``testbed.recorder``
(message counts).  ``log_time`` is when the recorder got a message
(CLOCK_REALTIME ns; t0 + k T in a simulation), ``publish_time`` t0 plus the
message's own time stamp when it has one.

Crash safety: the writer closes its chunk and flushes the file at least every
``flush_interval`` (0.5 s), so a recorder killed with SIGKILL leaves a file whose
every complete chunk ``read`` recovers (``Recording.truncated`` is then True).
"""

from __future__ import annotations

import gc
import io
import json
import os
import platform
import struct
import sys
import threading
import time
from collections import Counter, defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from ..wire import messages as msg
from . import schema

PROFILE = "testbed"           # MCAP header profile
_U64_MAX = 2**64 - 1          # MCAP times are uint64 ns
FORMAT_VERSION = "1"          # bump when a topic or field changes meaning

TELEMETRY_TOPICS = {r: f"/telemetry/{r}" for r in ("plant", "encoder", "controller", "attacker")}
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


def default_path(scenario_name: str, when: float | None = None, directory: str | Path | None = None,
                 run_id: str | None = None) -> Path:
    """``recordings/<scenario>-<UTC start, YYYYmmdd-HHMMSS>-<run id>.mcap`` (a suffix avoids an existing file).

    The directory is ``$TESTBED_RECORDINGS_DIR`` if set, else ``recordings/`` under the current directory.
    The run id makes the name unique to the run; the writer also creates the file exclusively.
    """
    if directory is None:
        directory = os.environ.get("TESTBED_RECORDINGS_DIR") or "recordings"
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime(time.time() if when is None else when))
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in (run_id or ""))[:80]
    base = Path(directory) / (f"{scenario_name}-{stamp}-{safe}" if safe else f"{scenario_name}-{stamp}")
    p = base.with_suffix(".mcap")
    i = 1
    while p.exists():
        p = Path(f"{base}-{i}.mcap")
        i += 1
    return p


def software_versions() -> dict[str, str]:
    from importlib import metadata

    out = {"python": sys.version.split()[0], "platform": platform.platform(), "format": FORMAT_VERSION}
    for dist in ("dos-testbed", "numpy", "scipy", "numba", "eclipse-zenoh", "mcap", "protobuf", "rerun-sdk"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    try:
        import subprocess

        root = Path(__file__).resolve().parents[2]
        if (root / ".git").exists():
            r = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                               text=True, timeout=5)
            if r.returncode == 0:
                out["git"] = r.stdout.strip()
    except Exception:  # noqa: BLE001 - git is optional
        pass
    return out


def _module_keys(prefix: str, ref: str, info: dict) -> dict[str, str]:
    bundled = info.get("module", "").startswith("plants.")  # ships with the testbed (testbed.software)
    return {f"{prefix}_ref": ref, f"{prefix}_module": info.get("module", ""), f"{prefix}_class": info.get("class", ""),
            f"{prefix}_file": info.get("file", ""), f"{prefix}_source": "" if bundled else info.get("source", ""),
            f"{prefix}_sha256": info.get("sha256", "")}


def scenario_metadata(sc, ref: str | None = None) -> dict[str, str]:
    """The ``testbed.scenario`` record: the scenario's name, TOML, reference, folder, plant and model modules."""
    from plants.refs import source_info

    out = {"name": sc.name, "toml": sc.source or "", "ref": ref or sc.name, "base_dir": sc.base_dir or ""}
    fmu = sc.plant.fmu is not None
    try:
        info = sc.plant.source_info()
    except (ValueError, AttributeError):
        info = {}
    out.update(_module_keys("plant", "" if fmu else (sc.plant.ref or sc.plant.name), info))
    model = sc.model
    if model is not None and (fmu or model.name != sc.plant.ref):  # a [model] that is not the plant's class
        import plants

        try:
            minfo = source_info(plants.resolve(model.name, model.base_dir or None))
        except ValueError:
            minfo = {}
        out.update(_module_keys("model", model.name, minfo))
    return out


class RecordingWriter:
    """Thread-safe MCAP writer of protobuf messages, flushed at least every ``flush_interval`` seconds."""

    def __init__(self, path: str | Path, *, flush_interval: float = 0.5, chunk_size: int = 1 << 20,
                 compression: str = "zstd", exclusive: bool = True):
        from mcap.writer import CompressionType, Writer

        from ..errors import BadInput

        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # exclusive create: two runs can never write into one file
            self._f = open(self.path, "xb" if exclusive else "wb")
        except FileExistsError:
            raise BadInput(f"{self.path} exists: a recording is never overwritten (remove it, choose another "
                           "path, or pass --force)") from None
        except OSError as e:
            raise BadInput(f"cannot write the recording {self.path}: {e.strerror or e}") from None
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
        self._w = Writer(self._f, chunk_size=chunk_size, compression=comp, enable_data_crcs=True)
        self._w.start(profile=PROFILE, library=f"testbed-recorder/{FORMAT_VERSION}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._lock = threading.Lock()
        self.flush_interval = float(flush_interval)
        self._last_flush = time.monotonic()
        self.counts: Counter = Counter()
        self.closed = False

    def _channel(self, topic: str, name: str) -> int:
        ch = self._channels.get(topic)
        if ch is None:
            sid = self._schemas.get(name)
            if sid is None:
                if "." in name:  # a Foxglove schema, as foxglove-sdk publishes it
                    from ..view.foxglove import descriptor_set

                    full, data = name, descriptor_set(name)
                else:
                    full, data = schema.full_name(name), schema.file_descriptor_set()
                sid = self._w.register_schema(name=full, encoding="protobuf", data=data)
                self._schemas[name] = sid
            ch = self._w.register_channel(topic=topic, message_encoding="protobuf", schema_id=sid)
            self._channels[topic] = ch
        return ch

    def metadata(self, name: str, data: dict) -> None:
        clean = {str(k): v if isinstance(v, str) else json.dumps(v, default=str) for k, v in data.items()}
        with self._lock:
            if not self.closed:
                self._w.add_metadata(name, clean)
                self._f.flush()

    def write(self, topic: str, obj, log_time: int, publish_time: int | None = None,
              name: str | None = None, extra: dict | None = None) -> None:
        """``obj``: a ``testbed.wire.messages`` dataclass, a dict with the schema's fields, or a protobuf message.

        ``extra``: fields beside the dataclass's (``foxglove_topics.telemetry_extra``).
        """
        if name is None:
            name = schema_for_topic(topic)
            if name is None:
                raise ValueError(f"{topic!r} is not a topic of a recording")
        data = obj.SerializeToString() if hasattr(obj, "SerializeToString") else \
            schema.to_pb(obj, name, extra).SerializeToString()
        self.write_bytes(topic, name, data, log_time, publish_time)

    def write_bytes(self, topic: str, name: str, data: bytes, log_time: int, publish_time: int | None = None) -> None:
        log_time = int(log_time)
        with self._lock:
            if self.closed:
                return
            ch = self._channel(topic, name)
            pub = int(log_time if publish_time is None else publish_time)
            self._w.add_message(channel_id=ch, log_time=min(max(log_time, 0), _U64_MAX),
                                data=data, publish_time=min(max(pub, 0), _U64_MAX))
            self.counts[topic] += 1
            if time.monotonic() - self._last_flush >= self.flush_interval:
                self._flush_locked()

    def maybe_flush(self) -> None:
        with self._lock:
            if not self.closed and time.monotonic() - self._last_flush >= self.flush_interval:
                self._flush_locked()

    def flush(self) -> None:
        with self._lock:
            if not self.closed:
                self._flush_locked()

    def _flush_locked(self) -> None:
        self._w.flush()   # closes the chunk in progress and flushes the stream (no fsync: a killed
        self._last_flush = time.monotonic()  # process's written data survives in the page cache)

    def close(self, recorder_stats: dict | None = None) -> None:
        with self._lock:
            if self.closed:
                return
            stats = {"messages": sum(self.counts.values()), "per_topic": dict(self.counts)}
            if recorder_stats:
                stats.update(recorder_stats)
            self._w.add_metadata("testbed.recorder", {k: json.dumps(v) for k, v in stats.items()})
            self._w.finish()
            self._f.close()
            self.closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


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
    telemetry: dict[str, dict[int, object]] = field(default_factory=lambda: {r: {} for r in TELEMETRY_TOPICS})
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

    def scenario(self):
        """The scenario the run used (``recorded_scenario``); sets ``plant_source``, ``model_source``."""
        sc, ps, ms = recorded_scenario(self.metadata, self.path, _cache=self)
        self.plant_source, self.model_source = ps, ms
        return sc


def recorded_scenario(metadata: dict[str, dict], path: str = "recording", *, _cache=None):
    """The scenario a recorded run used, rebuilt from the TOML stored in its metadata.

    Returns ``(scenario, plant_source, model_source)``.  The run's overrides are applied
    and what the run resolved (``testbed.resolved``: the quantizer, the timing) wins over
    this version's defaults.  The plant is imported as the run did (its reference, from
    the scenario's folder first); only when that fails is the plant module's source
    stored in the recording loaded, which runs code from the recording: a line on
    stderr says so.  ``plant_source`` tells which happened (``plants.refs.resolve_recorded``).
    """
    from ..scenario import ScenarioError, loads, with_overrides

    meta = metadata.get("testbed.scenario", {})
    toml = meta.get("toml")
    if not toml:
        raise ScenarioError(f"{path}: no scenario in the recording's metadata (not a recording of testbed run or "
                            "testbed simulate --out)")
    base_dir = meta.get("base_dir") or None
    if _cache is not None and getattr(_cache, "_resolved", False):  # once per recording: report and replay
        ps, ms = _cache.plant_source, _cache.model_source
    else:
        ps = _resolve_plant(meta, base_dir, "plant", path)
        ms = _resolve_plant(meta, base_dir, "model", path)
        if _cache is not None:
            _cache._resolved = True
    sc = loads(toml, name=str(meta.get("name", "recorded"))[:200], where=f"{path} (recorded scenario)",
               base_dir=base_dir, check_fmu=False)
    over = metadata.get("testbed.run", {}).get("scenario_overrides")
    try:
        sc = with_overrides(sc, json.loads(over)) if over else sc
    except (ValueError, TypeError) as e:
        raise ScenarioError(f"{path}: recorded overrides: {e}") from None
    return _with_resolved(sc, metadata.get("testbed.resolved")), ps, ms


def _resolve_plant(meta: dict, base_dir: str | None, prefix: str, path: str) -> dict | None:
    """Resolve the recorded plant (or model) reference, pinning the stored source when it is not importable."""
    from plants.refs import PlantRefError, resolve_recorded

    ref = meta.get(f"{prefix}_ref")
    if not ref:
        return None  # an FMU plant, a model that is the plant, or a recording from before references were stored
    try:
        _cls, status = resolve_recorded(ref, base_dir, module=meta.get(f"{prefix}_module", ""),
                                        class_name=meta.get(f"{prefix}_class", ""),
                                        source=meta.get(f"{prefix}_source", ""),
                                        sha256=meta.get(f"{prefix}_sha256", ""))
    except PlantRefError as e:
        from ..scenario import ScenarioError

        raise ScenarioError(f"{path}: {e}") from None
    status["module"] = meta.get(f"{prefix}_module", "")
    if status["loaded_from"] == "recording":
        print(f"note: {prefix} module {status['module']!r} is not importable ({status['reason']}); "
              f"loaded the source stored in {path} (sha256 {status['sha256'][:12]}): "
              "this runs code from the recording", file=sys.stderr)
    elif status["differs"]:
        print(f"note: {prefix} module {status['module']!r} as imported now differs from the one recorded "
              f"in {path} (sha256 {status['importable_sha256'][:12]} vs {status['sha256'][:12]})",
              file=sys.stderr)
    return status


def _with_resolved(sc, meta: dict | None):
    """``sc`` with the quantizer and timing the recorded run resolved (a later version's defaults
    may differ: the recording's own values win)."""
    import dataclasses

    from ..quantizer import QuantizerParams
    from ..scenario import DelaySpec, SimDelaySpec

    if not meta:
        return sc
    try:
        qd = json.loads(meta["quantizer"])
        rd = json.loads(meta["run"])
        qp = QuantizerParams(**qd)
        for key, cls in (("delay", DelaySpec), ("delay_lost", DelaySpec), ("sim_delay", SimDelaySpec)):
            if rd.get(key) is not None:
                v = dict(rd[key])
                if "values" in v:
                    v["values"] = tuple(v["values"])
                rd[key] = cls(**v)
        run = dataclasses.replace(sc.run, **rd)
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"unreadable testbed.resolved metadata: {e}") from None
    return dataclasses.replace(sc, quantizer=qp, run=run)


# the MCAP byte layout (the spec's records) that ``_records`` walks
_MAGIC = b"\x89MCAP0\r\n"
_OP_FOOTER, _OP_SCHEMA, _OP_CHANNEL, _OP_MESSAGE = 0x02, 0x03, 0x04, 0x05
_OP_CHUNK, _OP_METADATA, _OP_DATA_END = 0x06, 0x0C, 0x0F
_MSG_HEAD = struct.Struct("<HIQQ")      # Message record: channel id, sequence, log time, publish time
_CHUNK_HEAD = struct.Struct("<QQQI")    # message start, message end, uncompressed size, uncompressed crc


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


_IN_CHUNK = (_OP_MESSAGE, _OP_SCHEMA, _OP_CHANNEL)   # the records a chunk may hold


def _decode(op: int, buf: bytes, body: int, end: int):
    """A record whose body is ``buf[body:end]``: a Message as a plain ``(channel id, log time,
    data)`` tuple (the hot path: an ``mcap.records.Message`` costs a few us each), a Schema or
    Channel as the ``mcap`` record."""
    if op == _OP_MESSAGE:
        ch, _seq, lt, _pt = _MSG_HEAD.unpack_from(buf, body)
        return ch, lt, buf[body + _MSG_HEAD.size:end]
    from mcap.records import Channel, Schema

    return _body_record(Schema if op == _OP_SCHEMA else Channel, buf[body:end])


def _records(data: bytes):
    """The records of an MCAP file held in memory, in file order: ``(opcode, object)``.

    A plain loop over the byte layout (the MCAP spec's records), ~10x the
    ``mcap`` library's stream reader on small messages; message indexes and the
    summary section are skipped.  Raises ``_Truncated`` where a crash cut the file.
    """
    from mcap.records import Metadata

    n = len(data)
    off = len(_MAGIC)
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
        if op == _OP_CHUNK:
            _s, _e, size, _crc = _CHUNK_HEAD.unpack_from(data, body)
            p = body + _CHUNK_HEAD.size
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
        elif op == _OP_METADATA:
            yield op, _body_record(Metadata, data[body:end])
        elif op in (_OP_FOOTER, _OP_DATA_END):
            yield op, None
            if op == _OP_FOOTER:
                return
        off = end


@contextmanager
def no_gc():
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
    if not data.startswith(_MAGIC):
        raise ValueError(f"{path}: not an MCAP file")
    schemas: dict[int, dict[str, type]] = {}
    schema_names: dict[int, str] = {}
    channels: dict[int, tuple[str, str, type | None]] = {}
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
        if op == _OP_MESSAGE:
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
        elif op == _OP_SCHEMA:
            if r.encoding == "protobuf":
                try:
                    schemas[r.id] = {schema.full_name(k): v for k, v in schema.classes().items()} \
                        if r.data == schema.file_descriptor_set() else schema.classes_from(r.data)
                except Exception:  # noqa: BLE001 - an unreadable schema: its messages are counted only
                    schemas[r.id] = {}
            schema_names[r.id] = r.name
        elif op == _OP_CHANNEL:
            full = schema_names.get(r.schema_id, "")
            channels[r.id] = (r.topic, full.rsplit(".", 1)[-1], schemas.get(r.schema_id, {}).get(full))
        elif op == _OP_METADATA:
            rec.metadata[r.name] = dict(r.metadata)
        elif op == _OP_FOOTER:
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


def resolved_metadata(sc) -> dict[str, str]:
    """What the run resolved from its scenario: the quantizer's parameters (the delay-aware rule's
    nominal delays and margins included), the timing and its bounds (``testbed.resolved``)."""
    import dataclasses

    run = dataclasses.asdict(sc.run)
    return {"quantizer": json.dumps(dataclasses.asdict(sc.quantizer)), "run": json.dumps(run),
            "timing_params_ns": json.dumps([int(v) for v in sc.timing_params]), "L_u": json.dumps(sc.L_u),
            "K": json.dumps(sc.K.tolist()), "u_max": json.dumps(sc.controller.u_max)}


def write_text_metadata(w: RecordingWriter, sc, *, source: str, run_id: str, ref: str | None = None,
                        extra: dict | None = None) -> None:
    """The metadata every recording starts with."""
    w.metadata("testbed.scenario", scenario_metadata(sc, ref))
    w.metadata("testbed.resolved", resolved_metadata(sc))
    w.metadata("testbed.software", software_versions())
    run = {"source": source, "run_id": run_id, "host": platform.node(), "pid": str(os.getpid()),
           "command": " ".join(sys.argv), "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    if extra:
        run.update({k: v if isinstance(v, str) else json.dumps(v, default=str) for k, v in extra.items()})
    w.metadata("testbed.run", run)


def record_simulation(path: str | Path, sc, res, *, overrides: dict | None = None, ref: str | None = None,
                      t0_ns: int | None = None, flush_interval: float = 5.0, exclusive: bool = True,
                      roa: bool = True) -> dict:
    """Write a simulated run (``testbed.simulate.SimResult``) with the topics and schemas of a live run.

    Times are nominal and latencies zero (t_k = k T, every message at its sample
    instant); t0 is the wall-clock time of the call.  The Foxglove topics
    (``foxglove_topics``) come from the same tap as a live recorder's; ``roa``:
    draw the nominal region of attraction there.  Returns the writer's counts.
    """
    import numpy as np

    from ..quantizer import Codebook
    from ..simulate import attack_on_samples
    from ..view.foxglove import FoxgloveTopics, telemetry_extra

    t0 = time.time_ns() if t0_ns is None else int(t0_ns)
    Tn = int(round(sc.T * 1e9))
    N = len(res.t)
    plant = sc.make_model()
    cb = Codebook(plant.n, sc.quantizer.M, resilient=(sc.quantizer.mode == "resilient"))
    run_id = f"sim-{sc.name}-{t0}"
    w = RecordingWriter(path, flush_interval=flush_interval, exclusive=exclusive)
    fox = FoxgloveTopics(sc, roa=roa)

    def tap(items):
        for topic, name, data, lt in items:
            w.write_bytes(topic, name, data, lt)

    def tele(topic, name, t, lt):
        w.write(topic, t, lt, name=name, extra=telemetry_extra(name, t, t0, Tn))

    try:
        write_text_metadata(w, sc, source="simulate", run_id=run_id, ref=ref,
                            extra={"scenario_overrides": overrides or {}, "bits": cb.bits})
        start = msg.Start(run_id=run_id, t0_ns=t0, T_ns=Tn, n_steps=sc.n_steps, digest="", timing="ideal",
                          ack_via_attacker=False)
        w.write("/control/start", start, t0)
        tap(fox.start(start, t0))
        theta = np.asarray(res.theta, dtype=np.int64)
        attack_on = attack_on_samples(sc, res)  # an online attacker (greedy) is on when it drops
        dropped_total = np.cumsum(theta)
        prev_on = False
        delays = res.delays
        u_missing = res.u_missing if res.u_missing is not None else np.zeros(N, dtype=bool)
        withheld = res.withheld if res.withheld is not None else np.zeros(N, dtype=bool)
        reasons = res.reason
        fault = getattr(res, "plant_fault", None)   # the true plant failed (an FMU step) at plant_fault_at
        for k in range(N):
            tk = k * Tn
            lt = t0 + tk
            th = int(theta[k])
            dk = 0 if delays is None else int(delays[k])
            miss = bool(u_missing[k])
            p = msg.PlantTelemetry(
                k=k, t_ns=tk, sensor_tx_ns=tk, u_rx_ns=msg.NO_TIME if miss else tk + dk, delay_ns=dk,
                theta=msg.THETA_NONE if miss else th,
                flags=(msg.PlantTelemetry.FLAG_NO_U | msg.PlantTelemetry.FLAG_MISS) if miss else 0,
                flow_status=int(res.flow_status) if k == res.diverged_at else 0,
                x=tuple(res.x[k]), u=(0.0,) * res.u.shape[1] if miss else tuple(res.u[k]))
            tele("/telemetry/plant", "PlantSample", p, lt)
            tap(fox.plant(p, lt))
            if fault is not None and k == res.plant_fault_at:  # the event a live plant node publishes
                ev = msg.Event(node="plant", kind="plant_fault", k=k, t_ns=tk, detail=fault)
                w.write("/events/plant", ev, lt)
                tap(fox.event(ev, lt))
            sym = int(res.symbols[k])
            if withheld[k]:
                e = msg.EncoderTelemetry(k=k, sensor_tx_ns=tk, rx_ns=tk, tx_ns=msg.NO_TIME, symbol=-1, saturated=0,
                                         silent=1, E=float("nan"), xi=(), q=())
            else:
                e = msg.EncoderTelemetry(k=k, sensor_tx_ns=tk, rx_ns=tk, tx_ns=tk, symbol=sym,
                                         saturated=int(res.saturated[k]), silent=0, E=float(res.E_enc[k]),
                                         xi=tuple(res.xi_enc[k]), q=tuple(res.q_enc[k]))
            tele("/telemetry/encoder", "EncoderSample", e, lt)
            tap(fox.encoder(e, lt))
            if res.saturated[k]:
                ev = msg.Event(node="encoder", kind="saturation", k=k, t_ns=tk,
                               detail=f"x_k outside Q(xi_k, E_k), E_k = {res.E_enc[k]:.3e}")
                w.write("/events/encoder", ev, lt)
                tap(fox.event(ev, lt))
            on = bool(attack_on[k])
            tele("/telemetry/attacker", "AttackerSample", msg.AttackerTelemetry(
                k=k, rx_ns=tk, tx_ns=msg.NO_TIME if th else tk, dropped=th, corrupted=0, attack_on=int(on),
                dropped_total=int(dropped_total[k]), forwarded_total=int(k + 1 - dropped_total[k])), lt)
            if on != prev_on:
                st = msg.AttackerStatus(k=k, attack_on=on, dropped=int(dropped_total[k]),
                                        forwarded=int(k + 1 - dropped_total[k]))
                w.write("/attacker/status", st, lt)
                tap(fox.status(st, lt))
                prev_on = on
            reason = (msg.ControllerTelemetry.DEADLINE if th else msg.ControllerTelemetry.RECEIVED) \
                if reasons is None else int(reasons[k])
            received = reason == msg.ControllerTelemetry.RECEIVED
            tele("/telemetry/controller", "ControllerSample", msg.ControllerTelemetry(
                k=k, sym_stamp_ns=tk if received else msg.NO_TIME, rx_ns=tk if received else msg.NO_TIME, tx_ns=tk,
                symbol=sym if received else -1, theta=th, reason=reason,
                E=float(res.E_dec[k]), xi=tuple(res.xi_dec[k]), q=tuple(res.q[k]), u=tuple(res.u[k])), lt)
        tN = N * Tn
        tele("/telemetry/plant", "PlantSample", msg.PlantTelemetry(
            k=N, t_ns=tN, sensor_tx_ns=msg.NO_TIME, u_rx_ns=msg.NO_TIME, delay_ns=0, theta=msg.THETA_NONE,
            flags=msg.PlantTelemetry.FLAG_FINAL, flow_status=int(res.flow_status),
            x=tuple(np.asarray(res.x_final, dtype=float)), u=()), t0 + tN)
        if fault is not None and N == 0:  # the true plant failed to start
            w.write("/events/plant", msg.Event(node="plant", kind="plant_fault", k=0, t_ns=0, detail=fault), t0)
        stop = msg.Stop(reason="end of run" if fault is None else f"plant fault at sample {res.plant_fault_at}: {fault}",
                        origin="simulator")
        w.write("/control/stop", stop, t0 + tN)
        tap(fox.stop(stop, t0 + tN))
    finally:
        w.close()
    return dict(w.counts)


def markdown() -> str:
    """docs/recording-format.md: every topic, metadata record and field (``python -m testbed.record.recording``)."""
    doc = __doc__
    table = doc[doc.index("========================="):doc.index("Metadata records")].strip()
    return f"""# Recording format (MCAP + protobuf)

Generated by `python -m testbed.record.recording > docs/recording-format.md` from `testbed/record/recording.py` and
`testbed/record/schema.py`; a test checks that it is current.

Every live run (`testbed run`) and every `testbed simulate --out` writes one MCAP file.
Topics are the run's Zenoh keys without the `testbed/<run_id>` prefix. Every channel is
protobuf (schema encoding `protobuf`, a `FileDescriptorSet` of package `testbed`), so
Foxglove opens the file as it is and Rerun decodes it natively.

## Topics

```
{table}
```

## Metadata records

- `testbed.scenario`: `name`, `toml` (the scenario file's text), `ref` (as given on the command line),
  `base_dir` (the scenario file's folder, empty for a bundled scenario), `plant_ref` (`[plant] name`),
  `plant_module`, `plant_class`, `plant_file` (where the plant class came from), `plant_source` (that module's
  text; empty for the bundled plants, which ship with the testbed) and `plant_sha256` (its sha256; for an FMU
  plant `plant_ref` is empty, `plant_file` the FMU and `plant_sha256` the file's); the same `model_*` keys for a
  `[model]` of another class than the plant's.
  `testbed report` loads `plant_source` only when the module cannot be imported (see docs/own-plant.md).
- `testbed.software`: versions of Python, the platform, dos-testbed (and its git commit when run from a
  checkout), numpy, scipy, numba, eclipse-zenoh, mcap, protobuf, rerun-sdk; `format` (this format's version).
- `testbed.run`: `source` (`live` or `simulate`), `run_id`, `host`, `pid`, `command`, `started_utc`,
  `scenario_overrides` (JSON: `--duration`, `--T`, `--mode`, ... applied on top of the TOML), and for live
  runs `T_ns`, `ack_via_attacker`.
- `testbed.recorder` (written at a clean close only): message counts per topic and the recorder's counters.

## Times

`*_ns` fields are nanoseconds since the run's t0 (`/control/start`: `t0_ns`, CLOCK_REALTIME). A time that
never happened is an absent field (proto3 `optional`). A message's MCAP `log_time` is when the recorder
received it (CLOCK_REALTIME ns); its `publish_time` is t0 plus the message's own time stamp. In a
simulation both are t0 + k T and every latency is zero.

## Messages and fields

{schema.describe()}"""


__all__ = ["RecordingWriter", "Recording", "read", "default_path", "schema_for_topic",
           "record_simulation", "TELEMETRY_TOPICS", "LOOP_TOPICS", "software_versions", "write_text_metadata"]


if __name__ == "__main__":
    sys.stdout.write(markdown())
