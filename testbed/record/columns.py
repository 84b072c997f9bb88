"""Streaming, columnar reader of recordings: per-sample telemetry straight into numpy columns.

``read_columns(path)`` walks an MCAP file chunk by chunk (never the whole file
in memory) and decodes the four per-sample telemetry schemas
(``PlantSample``, ``EncoderSample``, ``ControllerSample``, ``AttackerSample``)
with a numba parser of the protobuf wire format, run over each decompressed
chunk, into preallocated columns: one row per sample k, no Python object per
message.  Everything else (events, attacker status, start / stop, node
summaries, liveliness, the recorder's malformed log) is rare and decoded with
the protobuf classes; the control path (``/loop/*``), the Foxglove topics and
channels of unknown schemas are counted, not decoded.

Trust (``testbed.common.errors.BadInput``, one line, exit 2):

* memory is sized by the scenario stored in the recording (N = its ``n_steps``)
  and capped by the file's size (at most ``ROW_BYTES_MIN`` bytes of file a
  sample, never by a number read from the file); telemetry whose k is outside
  [0, N) is rejected and counted (``Columns.rejected``);
* a chunk is decompressed only up to the size it declares, which is itself
  capped (``MAX_CHUNK_BYTES``, ``MAX_RATIO`` times its compressed size); at most
  ``MAX_KEPT`` events, status and liveliness messages are kept as objects;
* a chunk whose CRC fails, that does not decompress or whose records overrun it,
  a data section whose CRC fails, a record that runs past the end of a file that
  was closed (it ends with the MCAP magic), an invalid opcode: the file is
  corrupt and its results cannot be trusted (``CorruptRecording``);
* a file cut short (a killed recorder) is read up to its last complete chunk and
  marked ``truncated``;
* a telemetry message that is not well-formed protobuf of its schema (a varint
  that runs on, a vector whose length is not the scenario's n or m, a flag out of
  range) is rejected and counted (``Columns.malformed``), never half-written."""

from __future__ import annotations

import json
import struct
import zlib
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from ..wire import messages as msg
from ..wire.transport import ROLES  # the readers' role columns, in this order
from . import schema
from .mcapfile import (
    MSG_HEAD,
    OP_CHANNEL,
    OP_CHUNK,
    OP_DATA_END,
    OP_FOOTER,
    OP_MESSAGE,
    OP_SCHEMA,
    REC,
    CorruptRecording,
    _channel_record,
    _File,
    _schema_record,
    read_ahead,
    read_metadata,
)
from .topics import TELEMETRY_SCHEMA

if TYPE_CHECKING:
    from ..scenario import Scenario

ROW_BYTES_MIN = 8             # a recorded sample takes more file than this: rows <= file size / 8


MIN_ROWS = 1 << 16            # ... but room for this many samples whatever the file's size


MAX_FIELD = 64                # protobuf field numbers the parser maps (larger: skipped as unknown)


MAX_KEPT = 1_000_000          # events, attacker status, liveliness kept as objects (beyond: counted only)


# column groups of the parser (numba sees integer codes)
G_SKIP, G_I64, G_I32, G_U8, G_F64, G_VEC, G_K, G_U32 = range(8)


_U8_FIELDS = {"theta", "flags", "reason"}          # u32 fields whose values fit a byte (checked)


_VEC_WIDTH = {"x": "n", "xi": "n", "q": "n", "u": "m", "x_meas": "n"}


#: the value of a field in the rows of samples a role did not record (by default NaN for floats,
#: ``NO_TIME`` for optional times, 0 otherwise): what ``testbed report`` has always shown there
ABSENT = {("plant", "u"): 0.0, ("encoder", "symbol"): -1}


# channel modes
CH_UNKNOWN, CH_COUNT, CH_PYTHON, CH_TELEMETRY = 0, 1, 2, 3


_PY_SCHEMAS = {"Event", "AttackerStatus", "RunStart", "RunStop", "NodeSummary", "Liveliness", "Malformed"}


# ============================================================================ column layout
@dataclass(frozen=True)
class Col:
    """One decoded field of one role: ``group`` (G_*), first column in its group's table, width."""

    role: str
    name: str
    group: int
    col: int
    width: int          # 1 for scalars, n or m for vectors
    default: float      # value of the field when a message leaves it out (protobuf's default)
    absent: float       # value in the rows of samples the role did not record (see ``ABSENT``)


@dataclass
class Layout:
    """Where each telemetry field goes: the column tables (i64, i32, u8, f64) and the parser's map."""

    n: int
    m: int
    cols: dict[tuple[str, str], Col]
    widths: dict[int, int]                       # group table -> number of columns
    tgt: np.ndarray                              # (4 roles, MAX_FIELD, 3): group, col, width
    ranges: np.ndarray                           # (4 roles, 4 tables, 2): [lo, hi) of the role's columns
    defaults: dict[int, np.ndarray]              # table -> default value of each column (in a message)
    absent: dict[int, np.ndarray]                # table -> value of each column in rows never recorded
    flags_col: int                               # u8 column of the plant's flags (-1: not decoded)


_TABLE = {G_I64: 0, G_U32: 0, G_I32: 1, G_U8: 2, G_F64: 3, G_VEC: 3}   # group -> table


def _group(name: str, ftype: str) -> int:
    base = ftype.rstrip("?*")
    if name == "k":
        return G_K
    if ftype.endswith("*"):
        return G_VEC if base == "f64" else G_SKIP
    if base == "i64":
        return G_I64
    if base == "i32":
        return G_I32
    if base == "bool" or (base == "u32" and name in _U8_FIELDS):
        return G_U8
    if base == "u32":
        return G_U32
    if base == "f64":
        return G_F64
    return G_SKIP                                # message types (time stamps), strings, bytes


def layout(n: int, m: int, fields: set[str] | None = None) -> Layout:
    """The column layout for a plant of n states and m inputs; ``fields``: ``"role.field"`` names to keep."""
    cols: dict[tuple[str, str], Col] = {}
    width = {0: 0, 1: 0, 2: 0, 3: 0}
    tgt = np.zeros((len(ROLES), MAX_FIELD, 3), dtype=np.int32)
    ranges = np.zeros((len(ROLES), 4, 2), dtype=np.int64)
    defaults: dict[int, list] = {0: [], 1: [], 2: [], 3: []}
    absent: dict[int, list] = {0: [], 1: [], 2: [], 3: []}
    for r, role in enumerate(ROLES):
        lo = dict(width)
        for number, (name, ftype, _doc) in enumerate(schema.SPEC[TELEMETRY_SCHEMA[role]], start=1):
            g = _group(name, ftype)
            if g == G_SKIP or number >= MAX_FIELD:
                continue
            if g == G_K:
                tgt[r, number] = (G_K, 0, 1)
                continue
            keep = fields is None or f"{role}.{name}" in fields or (role == "plant" and name == "flags")
            if not keep:
                continue
            t = _TABLE[g]
            w = {"n": n, "m": m}[_VEC_WIDTH.get(name, "n")] if g == G_VEC else 1
            dflt = np.nan if g == G_VEC else (msg.NO_TIME if ftype.endswith("?") else 0)
            gone = ABSENT.get((role, name), np.nan if t == 3 else dflt)
            cols[(role, name)] = Col(role, name, g, width[t], w, dflt, gone)
            tgt[r, number] = (g, width[t], w)
            defaults[t] += [dflt] * w
            absent[t] += [gone] * w
            width[t] += w
        for t in range(4):
            ranges[r, t] = (lo[t], width[t])
    dt = {0: np.int64, 1: np.int32, 2: np.uint8, 3: np.float64}
    fc = cols.get(("plant", "flags"))
    return Layout(n, m, cols, width, tgt, ranges, {t: np.array(defaults[t], dtype=dt[t]) for t in range(4)},
                  {t: np.array(absent[t], dtype=dt[t]) for t in range(4)}, fc.col if fc else -1)


def _tables(L: Layout, rows: int, order: Literal["C", "F"] = "C", *, fill: bool = True) -> dict[int, np.ndarray]:
    """The four tables of ``rows`` rows, every field absent.  ``order="F"``: each column contiguous (what a
    recording's reader allocates: the summary reads a column at a time; docs/benchmarks.md, "Post-mortems against the
    disk"); the live collector's bounded buffers keep rows ("C").  ``fill=False``: not written at all (the reader's:
    the parser writes every column of a role in the rows it records, :func:`_fill_absent` the rest once read)."""
    out = {}
    for t, dt in ((0, np.int64), (1, np.int32), (2, np.uint8), (3, np.float64)):
        a = np.empty((rows, L.widths[t]), dtype=dt, order=order)
        if fill:
            a[...] = L.absent[t]
        out[t] = a
    return out


def _fill_absent(L: Layout, tables: dict[int, np.ndarray], present: np.ndarray) -> None:
    """Every column of role r in the rows r did not record (``present[:, r] == 0``): its value there
    (``Layout.absent``).  The role's columns are ``L.ranges[r, t]`` of each table; together the roles' ranges are
    every column, so tables made with ``fill=False`` read as :func:`_tables`' once the parser has written the rest."""
    for r in range(len(ROLES)):
        miss = np.flatnonzero(present[:, r] == 0)
        if not miss.size:
            continue
        for t in range(4):
            lo, hi = int(L.ranges[r, t, 0]), int(L.ranges[r, t, 1])
            if hi > lo:
                tables[t][miss, lo:hi] = L.absent[t][lo:hi]


# ============================================================================ the numba parser
def _kernels():
    """The wire-format parser (numba: compiled, or loaded from its cache, on the first call)."""
    from ._protobuf import walk  # here: importing the reader stays cheap until a file is read

    return walk


# ============================================================================ result
@dataclass
class Columns:
    """A recording, decoded: per-sample telemetry as columns, the rare messages as lists.

    ``get(role, field)`` is the column of one telemetry field (rows k = 0..rows-1;
    vectors (rows, width)); ``has(role)`` the rows that role recorded.  Fields of
    rows a role did not record hold their defaults (NaN, 0 or ``NO_TIME``).
    """

    path: str
    n: int
    m: int
    N: int                      # the scenario's n_steps
    rows: int                   # rows allocated: min(N, what the file's size can hold)
    lay: Layout
    tables: dict[int, np.ndarray]
    present: np.ndarray         # (rows, 4) uint8: messages accepted per role and sample
    final: dict | None = None   # the plant's final sample x_N: {"k", "x", "flow_status"}
    metadata: dict[str, dict] = field(default_factory=dict)
    start: msg.Start | None = None
    stops: list = field(default_factory=list)
    events: list = field(default_factory=list)
    status: list = field(default_factory=list)
    summaries: dict[str, dict] = field(default_factory=dict)
    liveliness: list = field(default_factory=list)  # (log ns, node, token, present)
    counts: Counter = field(default_factory=Counter)
    malformed: int = 0          # messages that did not decode (and the recorder's own malformed log)
    rejected: dict[str, int] = field(default_factory=dict)   # telemetry with k outside [0, N), by role
    duplicates: int = 0
    finals: int = 0             # plant messages of the final state x_N (the last one counts)
    unknown_channel: int = 0
    not_kept: int = 0           # events, status, liveliness beyond MAX_KEPT (counted, not kept)
    last_log_time: int = 0
    truncated: bool = False
    read_error: str | None = None
    plant_source: dict | None = None   # set by ``record.summary.load``: how the plant module was loaded
    model_source: dict | None = None   # ... and the [model]'s, when it is another class

    def get(self, role: str, name: str) -> np.ndarray:
        """The column (a view); a field that was not decoded reads as never recorded (a read-only array)."""
        c = self.lay.cols.get((role, name))
        if c is None:
            return _not_decoded(role, name, self.rows, self.n, self.m)
        t = self.tables[_TABLE[c.group]]
        return t[:, c.col] if c.group != G_VEC else t[:, c.col:c.col + c.width]

    def has(self, role: str) -> np.ndarray:
        return self.present[:, ROLES.index(role)] > 0

    def last_k(self, role: str) -> int:
        idx = np.flatnonzero(self.has(role))
        return int(idx[-1]) if idx.size else -1

    @property
    def source(self) -> str:
        return self.metadata.get("testbed.run", {}).get("source", "?")


def _not_decoded(role: str, name: str, rows: int, n: int, m: int) -> np.ndarray:
    spec = dict((f, t) for f, t, _ in schema.SPEC[TELEMETRY_SCHEMA[role]])
    if name not in spec:
        raise KeyError(f"{role} telemetry has no field {name!r}")
    g = _group(name, spec[name])
    dt = {0: np.int64, 1: np.int32, 2: np.uint8, 3: np.float64}[_TABLE.get(g, 3)]
    v = ABSENT.get((role, name), np.nan if dt is np.float64 else (msg.NO_TIME if spec[name].endswith("?") else 0))
    shape = (rows, {"n": n, "m": m}[_VEC_WIDTH.get(name, "n")]) if g == G_VEC else (rows,)
    return np.broadcast_to(np.array(v, dtype=dt), shape)


def normalize(c: "Columns") -> None:
    """Rows of silent encoder samples (a symbol withheld): xi, q, E not sent (NaN), symbol -1."""
    L = c.lay
    if ("encoder", "silent") not in L.cols:
        return
    silent = c.get("encoder", "silent") != 0
    if not silent.any():
        return
    for name, v in (("xi", np.nan), ("q", np.nan), ("E", np.nan), ("symbol", -1)):
        if ("encoder", name) in L.cols:
            c.get("encoder", name)[silent] = v


def scenario_of(metadata: dict[str, dict], path: str = "recording") -> Scenario:
    """The scenario a run used, rebuilt from its metadata (``recorded.recorded_scenario``)."""
    from .recorded import recorded_scenario

    return recorded_scenario(metadata, path)[0]


def rows_for(N: int, file_size: int) -> int:
    """Rows to allocate: the scenario's N, capped by what a file of this size can hold."""
    return int(max(0, min(int(N), max(MIN_ROWS, file_size // ROW_BYTES_MIN))))


class _Reader:
    def __init__(self, path: Path, sc, fields: set[str] | None):
        plant = sc.make_model()
        self.path = path
        self.sc = sc
        self.lay = layout(plant.n, plant.m, fields)
        self.size = path.stat().st_size
        N = int(sc.n_steps)
        rows = rows_for(N, self.size)
        L = self.lay
        # a column at a time (the summary's reductions read columns), and not written here: the parser is the first
        # to touch the pages of the rows it records, on the main thread while the read-ahead decompresses on the
        # other core; ``finish`` fills the rows a role did not record
        tables = _tables(L, rows, "F", fill=False)
        self.cols = Columns(path=str(path), n=plant.n, m=plant.m, N=N, rows=rows, lay=L, tables=tables,
                            present=np.zeros((rows, len(ROLES)), dtype=np.uint8))
        self.chan_mode = np.zeros(1 << 16, dtype=np.int8)
        self.chan_role = np.zeros(1 << 16, dtype=np.int8)
        self.chan_counts = np.zeros(1 << 16, dtype=np.int64)
        self.channels: dict[int, tuple[str, str]] = {}     # id -> (topic, schema short name)
        self.schemas: dict[int, tuple[str, str]] = {}      # id -> (full name, encoding)
        self.stats = np.zeros(8, dtype=np.int64)           # see _wire.walk
        self.role_stats = np.zeros((len(ROLES), 5), dtype=np.int64)
        self.final_tabs = {t: L.defaults[t].copy() for t in range(4)}
        self.final_k = np.full(1, -1, dtype=np.int64)
        self.py_pos = np.zeros(1, dtype=np.int64)
        self.classes: dict[str, Any] | None = None   # the protobuf classes, made at the first such message

    # ---- registry
    def schema_rec(self, body: bytes):
        sid, name, enc, _data = _schema_record(body)
        self.schemas[sid] = (name, enc)

    def channel_rec(self, body: bytes):
        cid, sid, topic, enc = _channel_record(body)
        full, senc = self.schemas.get(sid, ("", ""))
        short = full[len(schema.PACKAGE) + 1:] if full.startswith(schema.PACKAGE + ".") else ""
        self.channels[cid] = (topic, short)
        mode = CH_COUNT
        if enc == "protobuf" and senc == "protobuf" and short:
            role = topic.rsplit("/", 1)[-1]
            if topic.startswith("/telemetry/") and TELEMETRY_SCHEMA.get(role) == short:
                mode = CH_TELEMETRY
                self.chan_role[cid] = ROLES.index(role)
            elif short in _PY_SCHEMAS:
                mode = CH_PYTHON
        self.chan_mode[cid] = mode

    # ---- messages decoded in Python (rare)
    def py_message(self, buf, off: int, end: int):
        cid, _seq, log_time, _pt = MSG_HEAD.unpack_from(buf, off)
        topic, name = self.channels[cid]
        data = bytes(buf[off + MSG_HEAD.size:end])
        c = self.cols
        if self.classes is None:  # (while the read-ahead decompresses the next chunks)
            self.classes = schema.classes()
        try:
            m = self.classes[name].FromString(data)
        except Exception:  # noqa: BLE001 - protobuf DecodeError (and friends on crafted input)
            c.malformed += 1
            return
        if name in ("Event", "AttackerStatus", "Liveliness") and \
                len(c.events) + len(c.status) + len(c.liveliness) >= MAX_KEPT:
            c.not_kept += 1   # a decompression bomb of tiny messages must not fill the memory
            return
        if name == "Event":
            c.events.append(schema.from_pb(m, name))
        elif name == "AttackerStatus":
            c.status.append(schema.from_pb(m, name))
        elif name == "RunStart":
            if c.start is None:
                c.start = schema.from_pb(m, name)
        elif name == "RunStop":
            c.stops.append(schema.from_pb(m, name))
        elif name == "NodeSummary":
            try:
                d = json.loads(m.json)
                c.summaries[m.node] = d if isinstance(d, dict) else {"unparsed": m.json[:1000]}
            except ValueError:
                c.summaries[m.node] = {"unparsed": m.json[:1000]}
        elif name == "Liveliness":
            c.liveliness.append((log_time, m.node, m.token, m.present))
        elif name == "Malformed":
            c.malformed += 1

    # ---- a chunk's (or the file's unchunked) records
    def records(self, buf: bytes, where: int):
        walk = _kernels()
        arr = np.frombuffer(buf, dtype=np.uint8)
        L, c = self.lay, self.cols
        cap = len(buf) // 31 + 1
        if self.py_pos.size < cap:
            self.py_pos = np.zeros(cap, dtype=np.int64)
        pos = 0
        while True:
            pos, status, n_py = walk(arr, pos, self.chan_mode, self.chan_role, self.chan_counts, L.tgt, L.ranges,
                                     c.N, c.rows, c.tables[0], c.tables[1], c.tables[2], c.tables[3], c.present,
                                     L.defaults[0], L.defaults[1], L.defaults[2], L.defaults[3], L.flags_col,
                                     self.final_tabs[0], self.final_tabs[1], self.final_tabs[2],
                                     self.final_tabs[3], self.final_k, self.stats, self.role_stats, self.py_pos)
            for i in range(n_py):
                p = int(self.py_pos[i])
                (_op, ln) = REC.unpack_from(buf, p)
                self.py_message(buf, p + 9, p + 9 + ln)
            if status == 0:
                return
            if status == 2:
                raise CorruptRecording(f"{self.path}: corrupt recording: a record inside the chunk at byte "
                                       f"{where} runs past the chunk's end")
            op, ln = REC.unpack_from(buf, pos)
            body = buf[pos + 9:pos + 9 + ln]
            try:
                if op == OP_SCHEMA:
                    self.schema_rec(body)
                elif op == OP_CHANNEL:
                    self.channel_rec(body)
            except (ValueError, struct.error, UnicodeDecodeError):
                raise CorruptRecording(f"{self.path}: corrupt recording: unreadable schema or channel record "
                                       f"near byte {where}") from None
            pos += 9 + ln

    def run(self) -> Columns:
        fh = _File(self.path)
        c = self.cols
        data_crc = None
        self.records(b"", 0)  # the walk loaded (numba's cache) before the read-ahead starts, not while it waits
        items = read_ahead(fh, bodies={OP_CHUNK, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_DATA_END, OP_FOOTER}, crc=[0])
        try:
            for off, op, body, crc in items:
                if op is None:
                    if body is not None:
                        c.truncated, c.read_error = True, body
                    break
                if op == OP_CHUNK:
                    self.records(body, off)
                elif op in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE):
                    self.records(REC.pack(op, len(body)) + body, off)
                elif op == OP_DATA_END:
                    data_crc = struct.unpack_from("<I", body, 0)[0] if len(body) >= 4 else 0
                    if data_crc and data_crc != crc:
                        raise CorruptRecording(f"{self.path}: corrupt recording: the data section fails its CRC "
                                               "(the file was changed after it was written); its results "
                                               "cannot be trusted")
                elif op == OP_FOOTER:
                    self.check_summary(fh, off, body)
                    break
        finally:
            items.close()  # the read-ahead's thread stopped here, even when this walk raised (not when collected)
            fh.close()
        self.finish()
        return c

    def check_summary(self, fh: _File, off: int, body: bytes) -> None:
        """The footer's CRC of the summary section (what indexed readers such as Foxglove rely on)."""
        if body is None or len(body) < 20:
            raise CorruptRecording(f"{self.path}: corrupt recording: a footer of the wrong size at byte {off}")
        start, _offs, crc = struct.unpack_from("<QQI", body, 0)
        if not crc:
            return
        end = off + 9 + 16
        if start == 0:
            start = end - 9 - 16       # no summary section: the CRC covers the footer's own fields
        if not 0 < start <= off:
            raise CorruptRecording(f"{self.path}: corrupt recording: the footer points outside the file")
        fh.f.seek(start)
        got, left = 0, end - start
        while left > 0:
            b = fh.f.read(min(left, 1 << 20))
            if not b:
                break
            got = zlib.crc32(b, got)
            left -= len(b)
        if got != crc:
            raise CorruptRecording(f"{self.path}: corrupt recording: the summary section fails its CRC (the file "
                                   "was changed after it was written); its results cannot be trusted")

    def finish(self):
        c, L = self.cols, self.lay
        _fill_absent(L, c.tables, c.present)
        for cid, (topic, _name) in self.channels.items():
            if self.chan_counts[cid]:
                c.counts[topic] += int(self.chan_counts[cid])
        c.malformed += int(self.role_stats[:, 0].sum())
        c.rejected = {r: int(self.role_stats[i, 1] + self.role_stats[i, 3]) for i, r in enumerate(ROLES)
                      if self.role_stats[i, 1] + self.role_stats[i, 3]}
        c.duplicates = int(self.role_stats[:, 2].sum())
        c.finals = int(self.role_stats[0, 4])
        c.last_log_time = int(self.stats[0])
        c.unknown_channel = int(self.stats[1])
        normalize(c)
        if self.final_k[0] >= 0:
            x = self.final_tabs[3][L.cols[("plant", "x")].col:][:L.n] if ("plant", "x") in L.cols else \
                np.full(L.n, np.nan)
            fs = L.cols.get(("plant", "flow_status"))
            c.final = {"k": int(self.final_k[0]), "x": np.array(x, dtype=float),
                       "flow_status": int(self.final_tabs[1][fs.col]) if fs else 0}


def read_columns(path: str | Path, *, fields: set[str] | Callable[[dict], set[str] | None] | None = None,
                 sc: Scenario | None = None, metadata: dict[str, dict] | None = None) -> Columns:
    """Decode a recording into columns (see the module docstring).

    ``fields``: the ``"role.field"`` names to decode (default all), or a function of the file's metadata
    giving them; ``sc``: the scenario (default: the one stored); ``metadata``: the file's metadata records
    when the caller has read them (``mcapfile.read_metadata``: a walk of every record's header).
    Raises ``BadInput`` (exit 2) for a file that is not a recording, has no usable scenario, or is
    corrupt; a file cut short is read up to its cut.
    """
    path = Path(path)
    meta = metadata if metadata is not None else read_metadata(path)[0]  # BadInput: a directory, not MCAP, ...
    if sc is None:
        sc = scenario_of(meta, str(path))
    if callable(fields):
        fields = fields(meta)
    r = _Reader(path, sc, fields)
    r.cols.metadata = meta
    return r.run()


class ColumnBuilder:
    """Columns filled one telemetry dataclass at a time (the live collector's), same rules as a file.

    ``rows``: the samples to hold (the caller's highest accepted k + 1, at most the scenario's N);
    a record of a k outside them is rejected and counted, one whose vector has the wrong width is
    malformed.  ``add`` keeps no reference to the record: the columns are the only per-sample state.
    ``k0``: the sample of the first row (a window of a run's rows: ``testbed.live.collect.SpillRows``).
    """

    k0 = 0

    def __init__(self, sc, rows: int, fields: set[str] | None = None, *, events=(), status=(), summaries=None):
        plant = sc.make_model()
        L = layout(plant.n, plant.m, fields)
        rows = max(0, min(int(sc.n_steps), int(rows)))
        self.c = Columns(path="", n=plant.n, m=plant.m, N=int(sc.n_steps), rows=rows, lay=L,
                         tables=_tables(L, rows), present=np.zeros((rows, len(ROLES)), dtype=np.uint8),
                         events=list(events), status=list(status), summaries=dict(summaries or {}))
        self._mine = [[(key[1], col) for key, col in L.cols.items() if key[0] == role] for role in ROLES]

    def add(self, r: int, t: Any) -> None:
        """Record ``t`` (a telemetry dataclass) of role index ``r`` into row ``t.k``."""
        c = self.c
        k = t.k - self.k0
        if not 0 <= k < c.rows:
            c.rejected[ROLES[r]] = c.rejected.get(ROLES[r], 0) + 1
            return
        vals = []
        for name, col in self._mine[r]:
            v = getattr(t, name, None)
            if v is None:  # a field the wire dataclass does not carry (derived: log10_E)
                continue
            if col.group == G_VEC:
                v = v if len(v) else (col.default,) * col.width
                if len(v) != col.width:
                    c.malformed += 1
                    return
            vals.append((col, v))
        self._put(r, k, vals)

    def add_records(self, r: int, rec: np.ndarray, vectors: tuple[tuple[str, int], ...],
                    fields: tuple[str, ...]) -> None:
        """:meth:`add` of many records of role ``r`` at once: ``rec`` from :func:`decode_records` (one layout,
        ``vectors``), ``fields`` the names the role's telemetry dataclass carries.  The same rows, rejections
        and malformed counts as adding them one by one (a k appears once per role: the collector's spill)."""
        c = self.c
        rows = rec["k"].astype(np.int64) - self.k0
        ok = (rows >= 0) & (rows < c.rows)
        if not ok.all():
            c.rejected[ROLES[r]] = c.rejected.get(ROLES[r], 0) + int((~ok).sum())
            rows, rec = rows[ok], rec[ok]
        if not len(rows):
            return
        widths = dict(vectors)
        plan = []
        for name, col in self._mine[r]:
            if name not in fields:  # a field the wire dataclass does not carry (derived: log10_E)
                continue
            if col.group == G_VEC:
                w = widths.get(name, 0)
                if w and w != col.width:
                    c.malformed += len(rows)
                    return
                plan.append((col, rec[name] if w else col.default))
            else:
                plan.append((col, rec[name]))
        self._put(r, rows, plan)

    def _put(self, r: int, rows: int | np.ndarray, vals: list[tuple[Col, Any]]) -> None:
        """The values of role ``r`` into row(s) ``rows``, which are now present."""
        c = self.c
        for col, v in vals:
            tab = c.tables[_TABLE[col.group]]
            if col.group == G_VEC:
                tab[rows, col.col:col.col + col.width] = v
            else:
                tab[rows, col.col] = v
        c.present[rows, r] = 1

    def finish(self, plant_final: msg.PlantTelemetry | None = None) -> Columns:
        c = self.c
        if plant_final is not None:
            c.final = {"k": int(plant_final.k), "x": np.array(plant_final.x, dtype=float),
                       "flow_status": int(plant_final.flow_status)}
        normalize(c)
        return c


# ============================================================================ many records of one layout at once
#: numpy's name of each ``struct`` code the telemetry structs use (``testbed.wire.messages``)
_NP_OF_STRUCT = {"I": "<u4", "i": "<i4", "q": "<i8", "Q": "<u8", "H": "<u2", "h": "<i2", "B": "u1", "b": "i1",
                 "d": "<f8"}


def record_vectors(cls: type[msg._Telemetry], data: bytes, off: int, length: int) -> tuple[tuple[str, int], ...] | None:
    """The vectors (name, length) of the binary telemetry record of class ``cls`` at ``data[off:off + length]``,
    in the order ``cls.encode`` writes them; None where the record does not parse (``cls.decode`` says why)."""
    end, pos = off + length, off + cls._scalars.size
    if pos > end:
        return None
    out = []
    for name in cls._vector_fields:
        if pos >= end:
            return None
        out.append((name, data[pos]))
        pos += 1 + 8 * data[pos]
    if cls._optional_vector is not None and pos < end:
        if data[pos] == 0:  # never sent empty
            return None
        out.append((cls._optional_vector, data[pos]))
        pos += 1 + 8 * data[pos]
    return tuple(out) if pos == end else None


def record_dtype(cls: type[msg._Telemetry], vectors: tuple[tuple[str, int], ...]) -> np.dtype:
    """numpy's view of a record of ``cls`` whose vectors have these lengths, packed as ``cls.encode`` writes it."""
    codes = cls._scalars.format.lstrip("<")
    out: list[tuple] = [(name, _NP_OF_STRUCT[c]) for name, c in zip(cls._scalar_fields, codes, strict=True)]
    for name, w in vectors:
        out.append((f"{name}.n", "u1"))
        if w:
            out.append((name, "<f8", (w,)))
    dt = np.dtype(out)
    assert dt.itemsize == cls._scalars.size + sum(1 + 8 * w for _, w in vectors)
    return dt


def decode_records(cls: type[msg._Telemetry], buf: np.ndarray, offs: np.ndarray,
                   vectors: tuple[tuple[str, int], ...]) -> np.ndarray | None:
    """The records of ``cls`` at byte offsets ``offs`` of ``buf`` (uint8), all of one layout (``vectors``,
    from :func:`record_vectors` of one of them), as one structured array; None when one of them has another
    layout (a length byte differs: decode those one by one)."""
    dt = record_dtype(cls, vectors)
    rec = buf[offs[:, None] + np.arange(dt.itemsize)].view(dt)[:, 0]
    for name, w in vectors:
        if (rec[f"{name}.n"] != w).any():
            return None
    return rec


def from_records(sc: Scenario, tele: dict[str, dict[int, Any]], *, plant_final: msg.PlantTelemetry | None = None,
                 events: Iterable[msg.Event] = (), status: Iterable[msg.AttackerStatus] = (),
                 summaries: dict[str, dict] | None = None, fields: set[str] | None = None) -> Columns:
    """Columns from telemetry dataclasses by role and k (the live launcher's collector), same rules as a file."""
    ks = [k for d in tele.values() for k in d]
    b = ColumnBuilder(sc, max(ks) + 1 if ks else 0, fields, events=events, status=status, summaries=summaries)
    for r, role in enumerate(ROLES):
        for t in (tele.get(role) or {}).values():
            b.add(r, t)
    return b.finish(plant_final)


__all__ = ["Columns", "ColumnBuilder", "record_vectors", "record_dtype", "decode_records", "read_columns",
           "read_metadata", "from_records", "scenario_of", "layout",
           "CorruptRecording", "rows_for"]
