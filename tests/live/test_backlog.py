"""The recorder's queue (``testbed.nodes.backlog``): in order through memory and file, bounded in memory."""

from __future__ import annotations

import os
import random
import threading

from testbed.nodes.backlog import Backlog


def _items(n: int, rng: random.Random) -> list[tuple]:
    out = []
    for i in range(n):
        r = rng.random()
        if r < 0.1:  # liveliness, as Recorder._liveliness queues it
            out.append(("", None, (rng.choice(["plant", "encoder", "ünï"]), rng.choice(["alive", "ready"]),
                                   rng.random() < 0.5), 1_700_000_000_000_000_000 + i))
        else:
            att = None if r < 0.6 else rng.randbytes(rng.choice([0, 5, 12]))
            out.append((f"testbed/run/telemetry/{rng.choice(['plant', 'encoder'])}",
                        rng.randbytes(rng.choice([0, 1, 100, 2300, 70_000])), att, 1_700_000_000_000_000_000 + i))
    return out


def _drain(q: Backlog) -> list[tuple]:
    out = []
    while q:
        out.append(q.popleft())
    return out


def test_items_come_back_in_order_and_equal_through_memory_and_file(tmp_path):
    rng = random.Random(3)
    items = _items(3000, rng)
    q = Backlog(in_memory=50, directory=tmp_path)
    got = []
    for i, it in enumerate(items):
        assert q.append(it)
        if i % 7 == 0 and rng.random() < 0.5:  # the writer takes some now and then
            got += [q.popleft() for _ in range(min(len(q), rng.randint(0, 30)))]
        assert len(q._mem) <= 50  # the memory's bound, whatever the backlog
    assert q.max_len > 50 and q._spilled > 0
    got += _drain(q)
    assert got == items
    assert len(q) == 0 and q._wpos == 0  # drained: the file starts again from nothing
    q.close()
    assert os.listdir(tmp_path) == []    # the file has no name


def test_an_empty_backlog_raises_and_a_cleared_one_starts_again(tmp_path):
    q = Backlog(in_memory=2, directory=tmp_path)
    try:
        q.popleft()
        raise AssertionError("an empty backlog returned an item")
    except IndexError:
        pass
    items = _items(20, random.Random(1))
    for it in items:
        q.append(it)
    q.clear()
    assert len(q) == 0 and not q
    for it in items[:5]:
        q.append(it)
    assert _drain(q) == items[:5]
    q.close()


def test_one_writer_thread_and_the_reader_keep_the_order(tmp_path):
    items = _items(5000, random.Random(7))
    q = Backlog(in_memory=16, directory=tmp_path)
    done = threading.Event()

    def feed():
        for it in items:
            q.append(it)
        done.set()

    th = threading.Thread(target=feed)
    th.start()
    got = []
    while not (done.is_set() and not q):
        try:
            got.append(q.popleft())
        except IndexError:
            pass
    th.join()
    assert got == items
    q.close()


def test_an_item_the_file_cannot_take_is_refused(tmp_path):
    q = Backlog(in_memory=1, directory=tmp_path / "no such folder")
    assert q.append(("k", b"x", None, 1))
    assert not q.append(("k", b"y", None, 2))  # the file cannot be made: counted by the caller as lost
    assert _drain(q) == [("k", b"x", None, 1)]


def test_a_file_that_cannot_be_read_back_raises_and_a_cleared_backlog_goes_on(tmp_path):
    """A backlog file cut under the queue (a disk fault) is an ``OSError`` from ``popleft`` (the recorder counts
    what waited in it in ``write_errors``), never a wrong item; after ``clear`` the queue works again."""
    import pytest

    q = Backlog(2, tmp_path)
    items = _items(6, random.Random(3))
    for it in items:
        assert q.append(it)
    assert q.popleft() == items[0] and q.popleft() == items[1]
    os.ftruncate(q._fd, 0)  # the file's contents gone
    with pytest.raises(OSError):
        q.popleft()
    q.clear()
    assert not q and q.append(items[0]) and q.popleft() == items[0]
    q.close()
