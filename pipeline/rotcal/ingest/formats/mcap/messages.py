"""MCAP read message by message: the path for files ``mcap_fast`` declines,
and the one that words every error. Records are read by ``mcap_records``
(every declared size checked, chunks decompressed within the limit and
checked against their CRC); CDR messages are decoded by ``mcap_ros2`` with
rotcal's own definitions of the two message types it reads, as the fast path
decodes them by their fixed layouts."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from mcap.opcode import Opcode
from mcap.records import Channel, Schema
from mcap_ros2.decoder import DecoderFactory

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.formats.mcap.records import MESSAGE_FIELDS, McapFile, chunk_data, chunk_records, parse_channel, parse_schema, top_records
from rotcal.ingest.formats.mcap.ros2_msgdefs import IMU, IMU_SCHEMA, JOINT_SCHEMA, JOINT_STATE

_DEFINITIONS = {IMU_SCHEMA: IMU, JOINT_SCHEMA: JOINT_STATE}


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


def read_records(path: Path, topics: set[str], limits: Limits) -> dict[str, MessageTopic]:
    """Every channel by topic, with the raw messages of ``topics`` and of any
    Imu or JointState channel; refuses damaged files with the reason."""
    where = McapFile(path, limits)
    reader = _Reader(topics, where)
    with path.open("rb") as fh:
        for opcode, offset, length in top_records(fh, where):
            if opcode == Opcode.CHUNK:
                data = chunk_data(fh.read(length), offset, where)
                for inner, _, body in chunk_records(data, offset, where):
                    reader.record(inner, body)
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
                reader.record(opcode, fh.read(length))
    return reader.found


@dataclass
class _Reader:
    topics: set[str]
    where: McapFile
    found: dict[str, MessageTopic] = field(default_factory=dict)
    schemas: dict[int, Schema] = field(default_factory=dict)
    keep: dict[int, MessageTopic] = field(default_factory=dict)

    def record(self, opcode: int, body: bytes | memoryview) -> None:
        if opcode == Opcode.MESSAGE:
            if len(body) < MESSAGE_FIELDS.size:
                raise self.where.corrupt("a message record is shorter than its fields")
            channel_id, _, log_time, _ = MESSAGE_FIELDS.unpack_from(body)
            if (topic := self.keep.get(channel_id)) is not None:
                topic.stamps.append(log_time)
                topic.rows.append(bytes(body[MESSAGE_FIELDS.size :]))
        elif opcode == Opcode.SCHEMA:
            schema = parse_schema(body, self.where)
            self.schemas[schema.id] = schema
        elif opcode == Opcode.CHANNEL:
            channel = parse_channel(body, self.where)
            if channel.topic in self.found:
                self._another(self.found[channel.topic], channel)
                return
            topic = MessageTopic(self.schemas.get(channel.schema_id), channel, [], [])
            self.found[channel.topic] = topic
            kind = topic.schema.name if topic.schema is not None else ""
            if channel.topic in self.topics or kind in (IMU_SCHEMA, JOINT_SCHEMA):
                self.keep[channel.id] = topic


    def _another(self, topic: MessageTopic, channel: Channel) -> None:
        """A further channel of a topic already seen: its messages join the
        first channel's (a logger may split one topic over channels, e.g.
        one per session or per publisher) where both carry the same messages,
        else the topic is refused, naming both channels."""
        if topic.channel.id not in self.keep or channel.id == topic.channel.id:
            return
        schema = self.schemas.get(channel.schema_id)
        first = (topic.channel.message_encoding, topic.schema.name if topic.schema is not None else None)
        second = (channel.message_encoding, schema.name if schema is not None else None)
        if first != second:
            raise InputError(f"topic {channel.topic!r} is split over channels of different messages: channel "
                             f"{topic.channel.id} ({first[0]}, schema {first[1]!r}) and channel {channel.id} "
                             f"({second[0]}, schema {second[1]!r}); rotcal reads one kind of message per topic",
                             path=self.where.path)
        self.keep[channel.id] = topic


def require(schema: Schema | None, channel: Channel, expected: str, path: Path) -> None:
    """A DUT or table topic rotcal reads: JSON, or CDR of the ``expected``
    schema; any other is refused before a message is decoded."""
    encoding = channel.message_encoding
    if encoding not in ("cdr", "json"):
        raise InputError(f"topic {channel.topic!r} has message encoding {encoding!r}; rotcal reads cdr and json", path=path)
    name = schema.name if schema is not None else None
    if encoding == "cdr" and name != expected:
        raise InputError(f"topic {channel.topic!r} has schema {name!r}; rotcal reads {expected} (or JSON) there", path=path)


def decoder(topic: MessageTopic):
    """A message decoder for a topic ``require`` accepted."""
    if topic.channel.message_encoding == "json":
        return json.loads
    name = topic.schema.name if topic.schema is not None else ""
    return DecoderFactory().decoder_for("cdr", Schema(id=0, name=name, encoding="ros2msg", data=_DEFINITIONS[name].encode()))
