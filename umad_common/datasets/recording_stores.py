"""Where a recording's messages come from: one `MessageStore` per file format, each read with the
format's own library.

What is read, and with which library (no message parser of our own):

- a bare `.mcap`, or a rosbag2 folder (`metadata.yaml`) of one `.mcap` file: `mcap`, its messages
  decoded by `mcap-ros2-support` (ROS 2 CDR), `mcap-protobuf-support` (Foxglove schemas in protobuf)
  or `json`; the message times from the file's indexes, no payload read. zstd- and lz4-compressed
  chunks are read as they are. A file cut off by a crash is read up to the damage with
  `allow_truncated`;
- any other rosbag2 folder (SQLite3 storage, a split or file-compressed bag, IDL definitions) or a
  bare `.db3`: `rosbags`, which decodes ROS 2 CDR with the definitions the bag embeds (the ROS
  distribution's otherwise).
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from umad_common.datasets.drive import BAG_METADATA, UMAD_LOG_PROFILE, DatasetError, mcap_profile
from umad_common.datasets.recording_messages import EXTRA_DEFINITIONS, canonical_type, from_json


class MessageStore(ABC):
    """The messages of one recording file or folder, by topic and log time.

    Attributes:
        topics: topic -> canonical type.
        counts: topic -> messages.
        kind: what the recording is, for `umad data info`.
        truncated: why reading stopped before the end (a file cut off by a crash), else None.
    """

    topics: dict[str, str]
    counts: dict[str, int]
    kind: str
    truncated: str | None = None

    @abstractmethod
    def times(self, topics: list[str]) -> dict[str, np.ndarray]:
        """Each topic's message log times (ns, int64, in file order)."""

    @abstractmethod
    def messages(self, topics: list[str], start: int, stop: int) -> Iterator[tuple[str, int, Any]]:
        """(topic, log time, decoded message) of the topics' messages with start <= log time < stop."""

    def undecodable(self, topic: str) -> str | None:
        """Why the messages of `topic` cannot be decoded, or None."""
        return None


class RosbagStore(MessageStore):
    """A rosbag2 folder (MCAP or SQLite3 storage) or a bare .db3, read with `rosbags`."""

    def __init__(self, path: Path):
        from rosbags.highlevel import AnyReader

        self.path = path
        self.reader = AnyReader([path], default_typestore=ros_typestore())
        try:
            self.reader.open()
        except Exception as exc:  # rosbags raises its own and the storage's errors
            raise DatasetError(f"{path}: cannot be read as a ROS 2 bag ({type(exc).__name__}: {exc})") from None
        self.connections: dict[str, list] = {}
        for connection in self.reader.connections:
            self.connections.setdefault(connection.topic, []).append(connection)
        self.topics = {topic: canonical_type(conns[0].msgtype) for topic, conns in self.connections.items()}
        self.counts = {topic: sum(c.msgcount for c in conns) for topic, conns in self.connections.items()}
        storage = {".db3": "SQLite3", ".mcap": "MCAP"}.get(path.suffix, "")
        if path.is_dir():
            files = [p.suffix for p in path.iterdir() if p.suffix in (".db3", ".mcap")]
            storage = "SQLite3" if ".db3" in files else "MCAP"
        self.kind = f"ROS 2 bag, {storage} storage"
        self.lock = threading.Lock()

    def times(self, topics: list[str]) -> dict[str, np.ndarray]:
        found: dict[str, list[int]] = {topic: [] for topic in topics}
        conns = [c for topic in topics for c in self.connections[topic]]
        with self.lock:
            try:
                for connection, stamp, _ in self.reader.messages(connections=conns):
                    found[connection.topic].append(stamp)
            except Exception as exc:
                readable = sum(len(v) for v in found.values())
                self.truncated = f"unreadable after {readable} messages ({type(exc).__name__}: {exc})"
        return {topic: np.asarray(stamps, np.int64) for topic, stamps in found.items()}

    def messages(self, topics: list[str], start: int, stop: int) -> Iterator[tuple[str, int, Any]]:
        conns = [c for topic in topics for c in self.connections[topic]]
        with self.lock:
            raw = list(self.reader.messages(connections=conns, start=start, stop=stop))
        for connection, stamp, data in raw:
            try:
                message = self.reader.deserialize(data, connection.msgtype)
            except Exception as exc:
                raise DatasetError(
                    f"{self.path}: topic {connection.topic} ({connection.msgtype}): a message at {stamp} ns cannot "
                    f"be decoded ({exc}); expected {connection.msgtype} in CDR"
                ) from None
            yield connection.topic, stamp, message


def ros_typestore():
    """The newest ROS 2 distribution's message types plus the control types (EXTRA_DEFINITIONS)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.LATEST)
    for name, text in EXTRA_DEFINITIONS.items():
        store.register(get_types_from_msg(text, name))
    return store


class McapStore(MessageStore):
    """An MCAP file of ROS 2 (CDR), protobuf or JSON messages, read with `mcap` and the MCAP
    authors' decoders. Its message times come from the summary's chunk indexes and the message
    indexes beside each chunk, without reading a payload; a file without them (cut off by a crash)
    is read once in full, up to the damage. A frame then reads only the chunks that overlap its time."""

    def __init__(self, path: Path, kind: str | None = None):
        self.path = path
        self.file = open(path, "rb")  # noqa: SIM115 - held for the drive's life; frames seek in it
        self.lock = threading.Lock()
        self.schemas: dict[int, Any] = {}
        self.channels: dict[int, Any] = {}
        self.chunks: list[tuple[int, int, int]] = []  # (file offset, first, last log time)
        self.loose: list[tuple[int, int]] = []  # messages outside chunks: (file offset, log time)
        self.stamps: dict[int, list[int]] = {}  # channel id -> log times
        if not self.read_indexes():
            self.read_everything()
        self.by_topic: dict[str, list[int]] = {}
        for channel in self.channels.values():
            self.by_topic.setdefault(channel.topic, []).append(channel.id)
        self.topics = {topic: self.type_of(ids[0]) for topic, ids in self.by_topic.items()}
        self.counts = {topic: sum(len(self.stamps.get(i, [])) for i in ids) for topic, ids in self.by_topic.items()}
        encodings = sorted({self.channels[ids[0]].message_encoding for ids in self.by_topic.values()})
        self.kind = kind or f"MCAP, {' + '.join(encodings) or 'no'} messages"
        self.decoders: dict[int, Any] = {}

    def read_indexes(self) -> bool:
        """Schemas, channels, chunks and message times from the summary and the message indexes; False
        where the file has none, or they do not account for every message."""
        from mcap.reader import make_reader
        from mcap.stream_reader import StreamReader

        try:
            self.file.seek(0)
            summary = make_reader(self.file).get_summary()
        except Exception:  # no footer or summary: a file cut off by a crash
            return False
        if summary is None or summary.statistics is None or not summary.chunk_indexes:
            return False
        stamps: dict[int, list[int]] = {}
        for chunk in summary.chunk_indexes:
            for channel_id, offset in chunk.message_index_offsets.items():
                self.file.seek(offset)
                index = next(StreamReader(self.file, skip_magic=True).records)
                stamps.setdefault(channel_id, []).extend(stamp for stamp, _ in index.records)
        if sum(map(len, stamps.values())) != summary.statistics.message_count:
            return False  # messages outside chunks, or an index that misses some
        self.schemas, self.channels, self.stamps = dict(summary.schemas), dict(summary.channels), stamps
        self.chunks = [(c.chunk_start_offset, c.message_start_time, c.message_end_time) for c in summary.chunk_indexes]
        return True

    def read_everything(self) -> None:
        """One pass over every record: schemas, channels, chunks and message times, up to any damage."""
        from mcap.records import Channel, Chunk, Footer, Message, Schema
        from mcap.stream_reader import StreamReader, breakup_chunk

        self.file.seek(0)
        records = StreamReader(self.file, emit_chunks=True).records
        complete, count = False, 0
        while True:
            offset = self.file.tell()
            try:
                record = next(records)
            except StopIteration:
                break
            except Exception as exc:  # the mcap parser raises many types on a broken file
                self.truncated = f"cut off after {count} readable messages ({type(exc).__name__}: {exc})"
                break
            inner = breakup_chunk(record) if isinstance(record, Chunk) else [record]
            for item in inner:
                if isinstance(item, Schema):
                    self.schemas[item.id] = item
                elif isinstance(item, Channel):
                    self.channels[item.id] = item
                elif isinstance(item, Message):
                    self.stamps.setdefault(item.channel_id, []).append(item.log_time)
                    count += 1
                    if not isinstance(record, Chunk):
                        self.loose.append((offset, item.log_time))
            if isinstance(record, Chunk):
                self.chunks.append((offset, record.message_start_time, record.message_end_time))
            complete = complete or isinstance(record, Footer)
        if not complete and self.truncated is None:
            self.truncated = f"ends without its footer after {count} messages"

    def type_of(self, channel_id: int) -> str:
        schema = self.schemas.get(self.channels[channel_id].schema_id)
        return canonical_type(schema.name) if schema is not None else ""

    def decoder(self, channel_id: int):
        """The function decoding the channel's messages, or a string saying why there is none."""
        if channel_id in self.decoders:
            return self.decoders[channel_id]
        channel = self.channels[channel_id]
        schema = self.schemas.get(channel.schema_id)
        encoding = channel.message_encoding
        decoder: Any = f"message encoding {encoding!r} is not one of cdr (ROS 2), protobuf, json"
        try:
            if encoding == "json":
                decoder = from_json
            elif encoding == "cdr":
                from mcap_ros2.decoder import DecoderFactory as Ros2Decoders

                decoder = Ros2Decoders().decoder_for(encoding, schema) or "a cdr channel without a ros2msg schema"
            elif encoding == "protobuf":
                from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoders

                decoder = ProtobufDecoders().decoder_for(encoding, schema) or "a protobuf channel without its schema"
        except Exception as exc:  # a schema the decoder cannot build
            decoder = f"its schema cannot be read ({type(exc).__name__}: {exc})"
        self.decoders[channel_id] = decoder
        return decoder

    def undecodable(self, topic: str) -> str | None:
        decoder = self.decoder(self.by_topic[topic][0])
        return decoder if isinstance(decoder, str) else None

    def times(self, topics: list[str]) -> dict[str, np.ndarray]:
        return {
            topic: np.asarray(sum((self.stamps.get(i, []) for i in self.by_topic[topic]), []), np.int64)
            for topic in topics
        }

    def messages(self, topics: list[str], start: int, stop: int) -> Iterator[tuple[str, int, Any]]:
        from mcap.records import Chunk, Message
        from mcap.stream_reader import StreamReader, breakup_chunk

        wanted = {i for topic in topics for i in self.by_topic[topic]}
        found = []
        with self.lock:
            offsets = [o for o, first, last in self.chunks if first < stop and last >= start]
            offsets += [o for o, stamp in self.loose if start <= stamp < stop]
            for offset in sorted(offsets):
                self.file.seek(offset)
                record = next(StreamReader(self.file, skip_magic=True, emit_chunks=True).records)
                for item in breakup_chunk(record) if isinstance(record, Chunk) else [record]:
                    if isinstance(item, Message) and item.channel_id in wanted and start <= item.log_time < stop:
                        found.append(item)
        for item in sorted(found, key=lambda m: m.log_time):
            topic = self.channels[item.channel_id].topic
            try:
                message = self.decoder(item.channel_id)(item.data)
            except Exception as exc:
                raise DatasetError(
                    f"{self.path}: topic {topic} ({self.topics[topic]}): a message at {item.log_time} ns cannot be "
                    f"decoded ({type(exc).__name__}: {exc})"
                ) from None
            yield topic, item.log_time, message


def is_recording(path: Path) -> bool:
    """Whether `path` is a recording, from names and the MCAP header only: a folder with
    `metadata.yaml` (a rosbag2 folder), a `.db3` file, or a `.mcap` file that is not UMAD's own log
    (its profile `umad`)."""
    if path.is_dir():
        return (path / BAG_METADATA).is_file()
    if path.suffix == ".db3":
        return path.is_file()
    return path.suffix == ".mcap" and path.is_file() and mcap_profile(path) != UMAD_LOG_PROFILE


def open_store(path: Path) -> MessageStore:
    """The store of a recording: a bare .mcap, or a rosbag2 folder of one .mcap file (the usual bag of
    MCAP storage, uncompressed), with `mcap`; other rosbag2 folders (SQLite3 storage, split or
    file-compressed bags) and .db3 files with `rosbags`."""
    if path.is_dir() and not (path / BAG_METADATA).is_file():
        raise DatasetError(f"{path}: a folder without {BAG_METADATA}; expected a rosbag2 folder")
    if path.suffix == ".mcap" and path.is_file():
        return McapStore(path)
    storage = sorted(p for p in path.iterdir() if p.suffix in (".mcap", ".db3")) if path.is_dir() else []
    if len(storage) == 1 and storage[0].suffix == ".mcap":
        store = McapStore(storage[0], kind="ROS 2 bag, MCAP storage")
        if all(schema.encoding == "ros2msg" for schema in store.schemas.values()):
            return store
        store.file.close()  # IDL definitions: rosbags reads them
    return RosbagStore(path)
