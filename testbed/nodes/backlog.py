"""The recorder's queue of raw messages: the first ones in memory, the rest in an unnamed temporary file.

A Zenoh callback appends, the writer thread takes from the front, in order.  A writer slower than the
run (a recorder niced under a loaded CPU at 1 kHz) falls behind for as long as the run lasts; in memory
alone its backlog would take about 460 bytes a telemetry batch, i.e. memory per sample of the run.  Here
at most ``in_memory`` items are held; while more are waiting, new ones go to the end of the file and
come back to memory a block at a time, so the process holds a bounded amount, the disk the rest.  The
file has no name (``O_TMPFILE``): nothing is left behind, even after SIGKILL.
"""

from __future__ import annotations

import collections
import os
import struct
import tempfile
import threading
from pathlib import Path

#: an item's header in the file: log_time, kind, lengths of key, payload, attachment
_HEAD = struct.Struct("<qBIII")
#: kinds: a message without / with an attachment; a liveliness token present / gone
_MSG, _MSG_ATT, _ALIVE, _GONE = range(4)
#: bytes read from the file at a time (more when a single item is larger)
READ_BLOCK = 1 << 18


def _pack(item: tuple) -> bytes:
    key, payload, attachment, log_time = item
    if not key:  # liveliness: ("", None, (node, token, present), time)
        node, token, present = attachment
        k, p, a = node.encode("utf-8", "surrogateescape"), token.encode("utf-8", "surrogateescape"), b""
        kind = _ALIVE if present else _GONE
    else:
        k, p = key.encode("utf-8", "surrogateescape"), bytes(payload)
        a = b"" if attachment is None else bytes(attachment)
        kind = _MSG if attachment is None else _MSG_ATT
    return _HEAD.pack(log_time, kind, len(k), len(p), len(a)) + k + p + a


def _unpack(buf: bytes, pos: int) -> tuple[tuple, int] | None:
    """The item at ``pos`` of ``buf`` and the position after it, or None when ``buf`` ends before it does."""
    if pos + _HEAD.size > len(buf):
        return None
    log_time, kind, nk, np_, na = _HEAD.unpack_from(buf, pos)
    a0 = pos + _HEAD.size
    end = a0 + nk + np_ + na
    if end > len(buf):
        return None
    k = buf[a0:a0 + nk].decode("utf-8", "surrogateescape")
    p = buf[a0 + nk:a0 + nk + np_]
    if kind in (_ALIVE, _GONE):
        return ("", None, (k, p.decode("utf-8", "surrogateescape"), kind == _ALIVE), log_time), end
    return (k, p, buf[a0 + nk + np_:end] if kind == _MSG_ATT else None, log_time), end


class Backlog:
    """First in, first out: ``append`` (any thread) and ``popleft`` (one reader); ``len`` counts both parts.

    ``append`` returns False when an item could not be kept (the file could not be written): the caller
    counts it as lost.  ``max_len``: the longest the queue has been.
    """

    def __init__(self, in_memory: int = 4096, directory: str | Path | None = None):
        self.in_memory = max(1, int(in_memory))
        self.directory = directory
        self._mem: collections.deque = collections.deque()
        self._lock = threading.Lock()
        self._fd: int | None = None
        self._wpos = 0      # the file's end
        self._rpos = 0      # the first item not yet read back
        self._spilled = 0   # items in the file, not yet read back
        self.max_len = 0

    def __len__(self) -> int:
        return len(self._mem) + self._spilled

    def __bool__(self) -> bool:
        return bool(self._mem) or self._spilled > 0

    def append(self, item: tuple) -> bool:
        with self._lock:
            if not self._spilled and len(self._mem) < self.in_memory:
                self._mem.append(item)
            else:  # behind: after the items already in the file, to keep the order
                try:
                    data = _pack(item)
                    if self._fd is None:
                        self._fd = self._open()
                    n = 0
                    while n < len(data):
                        n += os.pwrite(self._fd, data[n:], self._wpos + n)
                except OSError:
                    return False
                self._wpos += len(data)
                self._spilled += 1
            n_all = len(self._mem) + self._spilled
            if n_all > self.max_len:
                self.max_len = n_all
            return True

    def _open(self) -> int:
        f = tempfile.TemporaryFile(dir=self.directory)
        fd = os.dup(f.fileno())
        f.close()
        return fd

    def popleft(self) -> tuple:
        """The oldest item; IndexError when there is none."""
        with self._lock:
            if not self._mem and self._spilled:
                self._refill()
            return self._mem.popleft()

    def _refill(self) -> None:
        """Up to ``in_memory`` items from the file's front back into memory (the lock is held)."""
        assert self._fd is not None
        size = READ_BLOCK
        while True:
            buf = os.pread(self._fd, min(size, self._wpos - self._rpos), self._rpos)
            pos = got_n = 0
            while got_n < self.in_memory:
                got = _unpack(buf, pos)
                if got is None:
                    break
                self._mem.append(got[0])
                pos = got[1]
                got_n += 1
            if pos:
                break
            if len(buf) < size:  # the file ends inside an item: cannot be (each append writes a whole one)
                raise OSError("the recorder's backlog file ends inside an item")
            size *= 2           # one item larger than the block
        self._rpos += pos
        self._spilled -= got_n
        if not self._spilled:  # all read back: the file starts again from nothing
            os.ftruncate(self._fd, 0)
            self._wpos = self._rpos = 0

    def clear(self) -> None:
        with self._lock:
            self._mem.clear()
            self._spilled = 0
            self._wpos = self._rpos = 0
            if self._fd is not None:
                try:
                    os.ftruncate(self._fd, 0)
                except OSError:
                    pass

    def close(self) -> None:
        with self._lock:
            self._mem.clear()
            self._spilled = 0
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None


__all__ = ["Backlog"]
