"""The MCAP byte layout (the records of the MCAP specification) that both readers walk -- the reference
reader (``testbed.record.reader``) and the columnar reader (``testbed.record.columns``) -- and the
walk of the columnar reader: record by record, sequentially, with the checks of a reader that never
trusts the file (the layout, the CRCs, the chunk sizes); the metadata records read alone
(``read_metadata``)."""

from __future__ import annotations

import struct
import threading
import zlib
from collections import deque
from collections.abc import Generator, Iterator
from pathlib import Path
from typing import Any

from ..common.errors import BadInput

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE = 0x01, 0x02, 0x03, 0x04, 0x05
OP_CHUNK, OP_METADATA, OP_DATA_END = 0x06, 0x0C, 0x0F
REC = struct.Struct("<BQ")              # a record's opcode and body length
MSG_HEAD = struct.Struct("<HIQQ")       # Message record: channel id, sequence, log time, publish time
CHUNK_HEAD = struct.Struct("<QQQI")     # message start, message end, uncompressed size, uncompressed crc




MAX_CHUNK_BYTES = 256 << 20   # largest decompressed chunk accepted (the recorder writes 1 MiB chunks)


MAX_RATIO = 200               # largest decompressed / compressed size of a chunk (ours: 4 to 15)


class CorruptRecording(BadInput):
    """A recording whose bytes fail a check (CRC, layout): its results cannot be trusted."""


# ============================================================================ the MCAP walk
class _File:
    """Records of an MCAP file read sequentially: (offset, opcode, body length); bodies on request."""

    def __init__(self, path: Path):
        self.path = path
        if path.is_dir():
            raise BadInput(f"{path}: is a directory, not a recording")
        try:
            self.f = open(path, "rb")
        except OSError as e:  # missing, unreadable: bad input (one line), as a file that is not MCAP
            raise BadInput(f"{path}: {e.strerror or e}") from None
        self.size = self.f.seek(0, 2)
        self.f.seek(0)
        head = self.f.read(len(MAGIC))
        if head != MAGIC:
            self.f.close()
            raise BadInput(f"{path}: not an MCAP file")
        self.f.seek(max(self.size - len(MAGIC), 0))
        self.closed_file = self.size >= 2 * len(MAGIC) and self.f.read(len(MAGIC)) == MAGIC
        self.f.seek(len(MAGIC))

    def close(self) -> None:
        self.f.close()


def _cut(fh: _File, what: str) -> str:
    """A record that does not fit: a cut file (truncated) or, in a file that was closed, corruption."""
    if fh.closed_file:
        raise CorruptRecording(f"{fh.path}: corrupt recording: {what}, in a file that ends as a finished "
                               "recording does; its results cannot be trusted")
    return f"cut short: {what}"


def _records(fh: _File, *, bodies: set[int], crc: list | None = None) -> Iterator[tuple]:
    """``(offset, op, body or None)`` in file order up to the footer; ``("cut", reason)`` at a cut.

    ``bodies``: the opcodes whose body is read (the others are skipped with a seek).
    ``crc``: a one-element list accumulating the CRC-32 of the data section (None: not computed).
    """
    f, size = fh.f, fh.size
    off = len(MAGIC)
    if crc is not None:
        crc[0] = zlib.crc32(MAGIC)
    in_data = True
    while True:
        if off + 9 > size:
            yield off, None, _cut(fh, "no footer" if off == size else f"record header cut at byte {off}")
            return
        f.seek(off)
        head = f.read(9)
        op, length = REC.unpack(head)
        end = off + 9 + length
        if end > size:
            yield off, None, _cut(fh, f"record (opcode {op:#x}) of {length} bytes at byte {off} runs past the "
                                      f"end of the file ({size} bytes)")
            return
        if op == 0 or 0x10 <= op < 0x80:
            raise CorruptRecording(f"{fh.path}: corrupt recording: invalid record opcode {op:#x} at byte {off}")
        if op == OP_DATA_END:
            in_data = False
        need = op in bodies or (crc is not None and in_data)
        body = f.read(length) if need else None
        if crc is not None and in_data and body is not None:  # read: ``need``
            crc[0] = zlib.crc32(body, zlib.crc32(head, crc[0]))
        yield off, op, body if op in bodies else None
        if op == OP_FOOTER:
            return
        off = end


AHEAD = 12                    # records read ahead of the reader at most (``read_ahead``; with 4, reading a
                              # recording of 1 MiB chunks, the parse waited or slowed down more often) ...
AHEAD_BYTES = 16 << 20        # ... and bytes of decompressed chunks: a larger chunk waits until the reader does


HAND_CRC = AHEAD // 3         # fewer records than this waiting: the reader checks the next chunk's CRC, not the
                              # thread (which decompresses, checks and reads ahead: the read's pace when it checks
                              # every CRC; docs/benchmarks.md, "Post-mortems against the disk")


def _chunk_size(body: bytes) -> int:
    """The decompressed size a chunk declares (0 if its header does not parse: ``_decompress`` says why)."""
    try:
        return int(CHUNK_HEAD.unpack_from(body, 0)[2])
    except struct.error:
        return 0


def read_ahead(fh: _File, *, bodies: set[int], crc: list) -> Generator[tuple, None, None]:
    """``_records`` with every chunk decompressed and checked (``_decompress``) by a second thread.  A chunk's
    CRC is checked by that thread or, when it is not far ahead (``HAND_CRC``), here, before the chunk is yielded.

    Yields ``(offset, op, body, crc)`` for the records whose opcode is in ``bodies`` (and the cut): a chunk's
    body is its records, ``crc`` the data section's CRC-32 up to this record.  zstd, lz4 and zlib's CRC release
    the GIL, so the next chunks are decompressed while the caller decodes this one (with a kernel that releases
    it too).  Memory: at most ``AHEAD`` records and ``AHEAD_BYTES`` of decompressed chunks wait; a chunk that
    declares more is decompressed only once the caller waits for it with nothing else held, so the largest
    chunk a file may declare (``MAX_CHUNK_BYTES``) is held once, as when reading in turn.  An error of the walk
    or of a chunk is raised here, in the caller's thread, at the record where it happened; the thread stops
    when the caller stops iterating."""
    cv = threading.Condition()
    items: deque[tuple[Any, int, int]] = deque()
    st = {"held": 0, "idle": False, "stop": False}
    done = object()

    def reserve(size: int = 0) -> bool:
        """Wait for room for one more record (``size`` bytes of it reserved before it is made); False: the
        caller stopped."""
        with cv:
            cv.wait_for(lambda: st["stop"] or (len(items) < AHEAD and (
                st["held"] + size <= AHEAD_BYTES or (not items and st["idle"]))))
            if st["stop"]:
                return False
            st["held"] += size
        return True

    def queue(item: object, size: int = 0, crc_left: int = 0) -> None:
        with cv:
            items.append((item, size, crc_left))
            cv.notify_all()

    def produce() -> None:
        try:
            for off, op, body in _records(fh, bodies=bodies, crc=crc):
                if op is not None and op not in bodies:
                    continue  # read for the CRC only (message indexes): not queued
                size = _chunk_size(body) if op == OP_CHUNK else 0
                if not reserve(size):
                    return
                left = 0
                if op == OP_CHUNK:
                    with cv:  # not far ahead of the reader: the reader checks this chunk's CRC (``HAND_CRC``)
                        hand = len(items) < HAND_CRC
                    body, left = _decompress(fh, off, body, check=not hand)
                queue((off, op, body, crc[0]), size, left)
                if op is None or op == OP_FOOTER:
                    break
            if reserve():
                queue(done)
        except BaseException as e:  # noqa: BLE001 - handed to the caller's thread, raised there
            if reserve():
                queue(e)

    t = threading.Thread(target=produce, name="mcap-read-ahead", daemon=True)
    t.start()
    try:
        while True:
            with cv:
                st["idle"] = True
                cv.notify_all()
                cv.wait_for(lambda: items)
                st["idle"] = False
                item, size, left = items.popleft()
                st["held"] -= size
                cv.notify_all()
            if item is done:
                return
            if isinstance(item, BaseException):
                raise item
            if left:
                _check_crc(fh, item[0], item[2], left)
            yield item
    finally:
        with cv:
            st["stop"] = True
            cv.notify_all()
        t.join()


def _metadata_record(body: bytes) -> tuple[str, dict[str, str]]:
    """A Metadata record's body: name, then a map of string pairs (the MCAP spec's layout)."""
    p = 0

    def string() -> str:
        nonlocal p
        (ln,) = struct.unpack_from("<I", body, p)
        if p + 4 + ln > len(body):
            raise ValueError("string runs past the record")
        s = body[p + 4:p + 4 + ln].decode()
        p += 4 + ln
        return s

    name = string()
    (maplen,) = struct.unpack_from("<I", body, p)
    p += 4
    end = p + maplen
    if end > len(body):
        raise ValueError("map runs past the record")
    out = {}
    while p < end:
        k = string()
        out[k] = string()
    return name, out


def _schema_record(body: bytes) -> tuple[int, str, str, bytes]:
    sid, nlen = struct.unpack_from("<HI", body, 0)
    p = 6
    name = body[p:p + nlen].decode()
    p += nlen
    (elen,) = struct.unpack_from("<I", body, p)
    enc = body[p + 4:p + 4 + elen].decode()
    p += 4 + elen
    (dlen,) = struct.unpack_from("<I", body, p)
    if p + 4 + dlen > len(body):
        raise ValueError("schema data runs past the record")
    return sid, name, enc, body[p + 4:p + 4 + dlen]


def _channel_record(body: bytes) -> tuple[int, int, str, str]:
    cid, sid, tlen = struct.unpack_from("<HHI", body, 0)
    p = 8
    topic = body[p:p + tlen].decode()
    p += tlen
    (elen,) = struct.unpack_from("<I", body, p)
    enc = body[p + 4:p + 4 + elen].decode()
    if p + 4 + elen > len(body):
        raise ValueError("channel record cut")
    return cid, sid, topic, enc


def read_metadata(path: str | Path) -> tuple[dict[str, dict], bool]:
    """Every Metadata record of a file (a fast pass that seeks over chunks), and whether it has a footer."""
    fh = _File(Path(path))
    out: dict[str, dict] = {}
    footer = False
    try:
        for _off, op, body in _records(fh, bodies={OP_METADATA}):
            if op == OP_METADATA:
                try:
                    name, d = _metadata_record(body)
                except (ValueError, struct.error, UnicodeDecodeError):
                    continue  # an unreadable metadata record: as if absent
                out[name] = d
            elif op == OP_FOOTER:
                footer = True
    finally:
        fh.close()
    return out, footer


def _decompress(fh: _File, off: int, body: bytes, *, check: bool = True) -> tuple[bytes, int]:
    """A chunk's records, checked: (records, the CRC left to check).  ``check=False``: the records' CRC is not
    computed here; the CRC the chunk declares (0: none) is returned for the caller to check (``_check_crc``)."""
    try:
        _s, _e, size, crc = CHUNK_HEAD.unpack_from(body, 0)
        p = CHUNK_HEAD.size
        (clen,) = struct.unpack_from("<I", body, p)
        compression = body[p + 4:p + 4 + clen].decode()
        p += 4 + clen
        (rlen,) = struct.unpack_from("<Q", body, p)
        p += 8
    except (struct.error, UnicodeDecodeError):
        raise CorruptRecording(f"{fh.path}: corrupt recording: unreadable chunk header at byte {off}") from None
    if p + rlen > len(body):
        raise CorruptRecording(f"{fh.path}: corrupt recording: the chunk at byte {off} holds fewer bytes than "
                               "it declares")
    data = memoryview(body)[p:p + rlen]   # not a copy: the compressed records are read where they lie
    if size > MAX_CHUNK_BYTES or size > max(MAX_RATIO * rlen, 1 << 20):
        raise CorruptRecording(f"{fh.path}: the chunk at byte {off} declares {size} bytes of records from "
                               f"{rlen} compressed bytes: more than this reader accepts")
    try:
        if compression == "zstd":
            import zstandard

            inner = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        elif compression == "lz4":
            import lz4.frame

            d = lz4.frame.LZ4FrameDecompressor()
            inner = d.decompress(data, max_length=size + 1)
        elif compression == "":
            inner = bytes(data)
        else:
            raise CorruptRecording(f"{fh.path}: the chunk at byte {off} uses compression {compression!r}, "
                                   "which this reader does not read")
    except CorruptRecording:
        raise
    except Exception as e:  # noqa: BLE001 - zstd / lz4 errors have no common base
        raise CorruptRecording(f"{fh.path}: corrupt recording: the chunk at byte {off} does not decompress "
                               f"({type(e).__name__}: {str(e)[:120]})") from None
    if len(inner) != size:
        raise CorruptRecording(f"{fh.path}: corrupt recording: the chunk at byte {off} decompresses to "
                               f"{len(inner)} bytes, not the {size} it declares")
    if not check:
        return inner, crc
    _check_crc(fh, off, inner, crc)
    return inner, 0


def _check_crc(fh: _File, off: int, inner: bytes, crc: int) -> None:
    if crc and zlib.crc32(inner) != crc:
        raise CorruptRecording(f"{fh.path}: corrupt recording: the chunk at byte {off} fails its CRC (changed "
                               "after it was written); its results cannot be trusted")
