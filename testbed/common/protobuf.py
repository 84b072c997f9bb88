"""Protobuf message classes from a serialized ``FileDescriptorSet``: the recording's schemas
(``testbed.record.schema``) and the Foxglove schemas (``testbed.view.foxglove``) alike."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from google.protobuf.message import Message


def varint(v: int) -> bytes:
    """``v`` as a base-128 varint, least significant group first: protobuf's (a negative ``v`` as its 64-bit
    two's complement) and the Thrift compact protocol's (``testbed.common.parquet``)."""
    out = bytearray()
    v &= (1 << 64) - 1
    while True:
        b = v & 0x7F
        v >>= 7
        if v:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def classes_from(fds_bytes: bytes) -> dict[str, type[Message]]:
    """Message classes (full name -> class) built from a serialized ``FileDescriptorSet``."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(fds_bytes)
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    out = {}
    for f in fds.file:
        for m in f.message_type:
            full = f"{f.package}.{m.name}" if f.package else m.name
            out[full] = message_factory.GetMessageClass(pool.FindMessageTypeByName(full))
    return out
