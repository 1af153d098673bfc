"""MCAP records as the file holds them, for both readers (``mcap_fast`` and
``mcap_messages``): every declared size is checked against what is there
before anything is read, allocated or decompressed, each chunk's CRC is
checked, and a record that does not fit is refused with the file and the
byte offset, never read short or skipped.

The ``mcap`` library's reader reads a message whose length runs past its
chunk as the rest of the chunk (the messages after it vanish), checks no
chunk CRC by default and decompresses whatever a chunk header claims; hence
this module.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import lz4.frame
import zstandard
from mcap.opcode import Opcode
from mcap.records import Channel, Schema
from zlib_ng import zlib_ng

from rotcal.config import Limits
from rotcal.errors import InputError, LimitError


class Unsupported(Exception):
    """The file holds something the fast path does not decode: the caller reads it with the per-message path."""

MAGIC = b"\x89MCAP0\r\n"
# Schema and channel records (and other non-message records) the chunks of
# one file may hold: each costs a Python call, and a chunk of a few kilobytes
# can expand to millions of tiny records. A capture has a schema and a
# channel per topic (per topic and chunk, if a writer repeats them).
MAX_DEFINITIONS = 100_000
_CHUNK_HEAD = struct.Struct("<QQQI")  # message start and end time, uncompressed size and CRC
MESSAGE_FIELDS = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time: then the data


@dataclass
class McapFile:
    """The file being read: its path (for messages), its limits and the
    count of non-message records read from its chunks so far."""

    path: Path
    limits: Limits
    definitions: int = 0

    def corrupt(self, problem: str) -> InputError:
        return InputError(f"corrupt MCAP: {problem}", path=self.path)

    def define(self) -> None:
        self.definitions += 1
        if self.definitions > MAX_DEFINITIONS:
            raise LimitError(f"more than {MAX_DEFINITIONS} schema, channel and other non-message records in chunks",
                             path=self.path)


def top_records(fh: BinaryIO, where: McapFile) -> Iterator[tuple[int, int, int]]:
    """(opcode, offset, body length) of each top-level record up to the
    footer, ``fh`` positioned at the body; each body lies inside the file and
    within the record limit."""
    size = os.fstat(fh.fileno()).st_size
    if fh.read(8) != MAGIC:
        raise where.corrupt("no MCAP magic at the start of the file")
    offset = 8
    while True:
        head = fh.read(9)
        if len(head) < 9:
            raise InputError(f"truncated MCAP: the file ends inside a record at byte {offset}", path=where.path)
        opcode, length = struct.unpack("<BQ", head)
        if opcode == 0:  # reserved: zeros where a record should start
            raise where.corrupt(f"a record of opcode 0 at byte {offset}")
        if length > where.limits.max_mcap_record_bytes:
            raise LimitError(f"an MCAP record is larger than the limit of {where.limits.max_mcap_record_bytes} bytes "
                             f"(byte {offset} declares {length})", path=where.path)
        if length > size - offset - 9:
            raise InputError(f"truncated MCAP: the file ends inside a record (byte {offset} declares {length} bytes, "
                             f"{size - offset - 9} remain)", path=where.path)
        yield opcode, offset, length
        offset += 9 + length
        fh.seek(offset)
        if opcode == Opcode.FOOTER:
            if fh.read(8) != MAGIC:
                raise where.corrupt("no MCAP magic at the end of the file")
            return


def chunk_data(body: bytes, offset: int, where: McapFile, out: memoryview | None = None) -> memoryview:
    """A chunk record's records, decompressed within the limit into ``out``
    (a buffer of the size the chunk declares; by default a new one) and
    checked against the chunk's CRC (when not zero, as the MCAP
    specification says)."""
    if len(body) < _CHUNK_HEAD.size + 4:
        raise where.corrupt(f"the chunk at byte {offset} is shorter than its header")
    _, _, size, crc = _CHUNK_HEAD.unpack_from(body)
    limit = where.limits.max_mcap_record_bytes
    if size > limit:
        raise LimitError(f"an MCAP chunk expands to {size} bytes, above the limit of {limit} bytes", path=where.path)
    (name_len,) = struct.unpack_from("<I", body, _CHUNK_HEAD.size)
    start = _CHUNK_HEAD.size + 4 + name_len + 8
    if start > len(body):
        raise where.corrupt(f"the chunk at byte {offset} is shorter than its header")
    compression = body[_CHUNK_HEAD.size + 4 : start - 8].decode(errors="replace")
    (data_len,) = struct.unpack_from("<Q", body, start - 8)
    if data_len > len(body) - start:  # fewer is allowed: records may gain fields at their end
        raise where.corrupt(f"the chunk at byte {offset} declares {data_len} bytes of records where it holds "
                            f"{len(body) - start}")
    out = memoryview(bytearray(size)) if out is None else out
    try:
        decompress(compression, memoryview(body)[start : start + data_len], out)
    except (zstandard.ZstdError, RuntimeError) as exc:
        raise where.corrupt(f"the chunk at byte {offset} does not decompress ({exc})") from None
    except ValueError as exc:
        raise where.corrupt(f"{exc}") from None
    if crc and zlib_ng.crc32(out) != crc:
        raise where.corrupt(f"the chunk at byte {offset} fails its CRC check")
    return out


def decompress(compression: str, data: memoryview, out: memoryview) -> None:
    """Decompressed into ``out`` (zstd: in place, no copy, the GIL released),
    reading at most one byte more whatever the compressed frame claims (a
    frame header can declare any content size); raises ValueError if that
    is not exactly ``len(out)`` bytes."""
    size = len(out)
    if compression == "zstd":
        reader, got = zstandard.ZstdDecompressor().stream_reader(data), 0
        while got < size and (n := reader.readinto(out[got:])):
            got += n
        got += len(reader.read(1)) if got == size else 0
    elif compression in ("lz4", ""):
        whole = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=size + 1) if compression else data
        got = len(whole)
        if got == size:
            out[:] = whole
    else:
        raise ValueError(f"chunk compression {compression!r}")
    if got != size:
        raise ValueError(f"a chunk holds {got} bytes where it declares {size}")


def chunk_records(data: bytes | memoryview, offset: int, where: McapFile) -> Iterator[tuple[int, int, memoryview]]:
    """(opcode, position, body) of each record in a chunk's ``data`` (a
    chunk at ``offset``, or a stretch of one); each record must fit."""
    view, pos = memoryview(data), 0
    while pos < len(view):
        if len(view) - pos < 9:
            raise where.corrupt(f"the chunk at byte {offset} ends inside a record at its byte {pos}")
        opcode, length = struct.unpack_from("<BQ", view, pos)
        if opcode == 0:
            raise where.corrupt(f"a record of opcode 0 at byte {pos} of the chunk at byte {offset}")
        if length > len(view) - pos - 9:
            raise where.corrupt(f"a record at byte {pos} of the chunk at byte {offset} declares {length} bytes "
                                f"where {len(view) - pos - 9} remain")
        if opcode != Opcode.MESSAGE:
            where.define()
        yield opcode, pos, view[pos + 9 : pos + 9 + length]
        pos += 9 + length


class _Fields:
    """A record's fields read in order, each checked to lie inside it."""

    def __init__(self, body: bytes | memoryview, what: str, where: McapFile):
        self.body, self.pos, self.what, self.where = memoryview(body), 0, what, where

    def take(self, n: int) -> memoryview:
        if n > len(self.body) - self.pos:
            raise self.where.corrupt(f"{self.what} is shorter than its fields")
        self.pos += n
        return self.body[self.pos - n : self.pos]

    def int(self, fmt: str) -> int:
        return struct.unpack(fmt, self.take(struct.calcsize(fmt)))[0]

    def text(self) -> str:
        return bytes(self.take(self.int("<I"))).decode(errors="replace")


def parse_schema(body: bytes | memoryview, where: McapFile) -> Schema:
    f = _Fields(body, "a schema record", where)
    return Schema(id=f.int("<H"), name=f.text(), encoding=f.text(), data=bytes(f.take(f.int("<I"))))


def parse_channel(body: bytes | memoryview, where: McapFile) -> Channel:
    f = _Fields(body, "a channel record", where)
    channel_id, schema_id, topic, encoding = f.int("<H"), f.int("<H"), f.text(), f.text()
    pairs = _Fields(f.take(f.int("<I")), "a channel's metadata", where)
    metadata = {}
    while pairs.pos < len(pairs.body):
        key = pairs.text()
        metadata[key] = pairs.text()
    return Channel(id=channel_id, schema_id=schema_id, topic=topic, message_encoding=encoding, metadata=metadata)
