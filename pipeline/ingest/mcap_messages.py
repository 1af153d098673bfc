"""MCAP read message by message (the ``mcap`` library's reader): the path
for files ``mcap_fast`` declines, and the one that words every error.
A chunk is never decompressed beyond the configured limit."""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, replace
from pathlib import Path

import zstandard
from mcap.exceptions import McapError
from mcap.reader import StreamReader
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import breakup_chunk
from mcap_ros2.decoder import DecoderFactory

from rotcal.config import Limits
from rotcal.errors import InputError, LimitError
from rotcal.ingest.mcap_columns import Unsupported
from rotcal.ingest.mcap_fast import decompress_chunk
from rotcal.ingest.ros2_msgdefs import IMU_SCHEMA, JOINT_SCHEMA


@dataclass
class MessageTopic:
    """One channel's raw messages: log times and payloads, in file order."""

    schema: Schema | None
    channel: Channel
    stamps: list
    rows: list

    @property
    def count(self) -> int:
        return len(self.rows)


def _chunk_records(chunk: Chunk, limit: int, path: Path) -> list:
    """A chunk's records, never decompressing more than ``limit`` bytes: a
    chunk of a few kilobytes can expand a million-fold, and the mcap library
    would allocate whatever its header claims."""
    if chunk.uncompressed_size > limit:
        raise LimitError(f"an MCAP chunk expands to {chunk.uncompressed_size} bytes, above the limit of {limit} bytes", path=path)
    try:
        data = decompress_chunk(chunk.compression, chunk.data, chunk.uncompressed_size)
    except Unsupported as exc:
        raise InputError(f"corrupt MCAP: {exc}", path=path) from None
    return breakup_chunk(replace(chunk, compression="", data=data))


def read_records(path: Path, topics: set[str], limits: Limits) -> dict[str, MessageTopic]:
    """Every channel by topic, with the raw messages of ``topics`` and of any
    Imu or JointState channel; refuses damaged files with the reason."""
    found: dict[str, MessageTopic] = {}
    schemas: dict[int, Schema] = {}
    keep: dict[int, MessageTopic] = {}
    try:
        with path.open("rb") as fh:
            limit = limits.max_mcap_record_bytes
            for record in (r for outer in StreamReader(fh, record_size_limit=limit, emit_chunks=True).records
                           for r in (_chunk_records(outer, limit, path) if isinstance(outer, Chunk) else [outer])):
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel) and record.topic not in found:
                    topic = MessageTopic(schemas.get(record.schema_id), record, [], [])
                    found[record.topic] = topic
                    kind = topic.schema.name if topic.schema is not None else ""
                    if record.topic in topics or kind in (IMU_SCHEMA, JOINT_SCHEMA):
                        keep[record.id] = topic
                elif isinstance(record, Message) and record.channel_id in keep:
                    topic = keep[record.channel_id]
                    topic.stamps.append(record.log_time)
                    topic.rows.append(record.data)
    except McapError as exc:
        if type(exc).__name__ == "RecordLengthLimitExceeded":
            raise LimitError(
                f"an MCAP record is larger than the limit of {limits.max_mcap_record_bytes} bytes", path=path
            ) from None
        if type(exc).__name__ == "EndOfFile":
            raise InputError("truncated MCAP: the file ends inside a record", path=path) from None
        raise InputError(f"corrupt MCAP: {exc}", path=path) from None
    except (struct.error, ValueError, EOFError, OSError, zstandard.ZstdError, RuntimeError) as exc:
        raise InputError(f"corrupt MCAP: {exc}", path=path) from None
    return found


def decoder(topic: MessageTopic, path: Path):
    encoding = topic.channel.message_encoding
    if encoding == "json":
        return lambda data: json.loads(data)
    if encoding == "cdr" and topic.schema is not None:
        return DecoderFactory().decoder_for(encoding, topic.schema)
    raise InputError(
        f"topic {topic.channel.topic!r} has message encoding {encoding!r}; rotcal reads cdr and json", path=path
    )
