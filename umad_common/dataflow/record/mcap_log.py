"""MCAP logs of the bus: the recorder that writes them and the reader that survives a truncated file.

Every bus message is stored as its exact payload bytes: one channel per Zenoh key,
`message_encoding` "msgpack", `sequence` = the frame's seq, `publish_time` = the source stamp, and
`log_time` = the source stamp too where it is a recording's own clock (a ROS 2 bag's or an MCAP's:
after RECORDING_CLOCK_START_NS), so the log opens in Foxglove on the recording's timeline beside the
recording itself; the time of writing otherwise (AnoVox drives are stamped from 0). The
graph and the package version are stored as metadata `umad`; whether the recording is complete (the
payloads it lost and the frames each channel lacks, see `umad_common/dataflow/record/recorder.py`) as metadata
`umad_recording`, written when the log is closed. Views of the messages may sit beside them:
JSON messages of JSON schemas on channels of their own, made by the `LogViews` class the graph names
(`record_views`: by default the Foxglove views, `viz/...` channels, `umad_common/viz/foxglove.py`,
which the engine never imports); replay ignores those.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from umad_common.dataflow.api.messages import Message as BusMessage
from umad_common.dataflow.api.messages import MessageError, decode

RECORDING_METADATA = "umad_recording"  # the recorder's account of what it could not record

log = logging.getLogger("umad.record")
RECORDING_CLOCK_START_NS = 946_684_800 * 10**9  # 2000-01-01: a stamp after it is a recording's own clock


def log_time_of(stamp_ns: int) -> int:
    """A message's MCAP log time: its stamp where that is a recording's clock, else now."""
    return stamp_ns if stamp_ns >= RECORDING_CLOCK_START_NS else time.time_ns()


class LogError(ValueError):
    """A log that cannot be read (fully): says where it broke and how many messages were readable."""

    def __init__(self, message: str, readable: int = 0):
        self.readable = readable
        super().__init__(message)


def package_version() -> str:
    try:
        return version("umad")
    except PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class View:
    """One message a log's views add: a JSON `body` of the JSON schema named `schema`, on `topic`."""

    topic: str
    schema: str
    body: dict


class LogViews(ABC):
    """Views of a log's bus messages, written beside their exact payloads: what a viewer shows of a
    run (the Foxglove views, `umad_common.viz.foxglove.FoxgloveViews`, are the default; the graph's
    `record_views` names the class, `package.module:Class`, loaded through `api/plugins.py`).

    The recorder makes one per log, `cls(mask_sources)` (map channel `op/output` -> the masks
    channel that refined it: the graph's wiring), and hands it every message that carries arrays, in
    the order they were recorded, on a thread of its own.
    """

    @abstractmethod
    def of(self, channel: str, msg: BusMessage) -> list[View]:
        """The views of one bus message on `channel` (`op/output`); [] for none."""

    @abstractmethod
    def schema(self, name: str) -> dict:
        """The JSON schema a view's `schema` names, stored once per log."""


class McapRecorder:
    """Thread-safe writer: `write(key, payload)` from Zenoh callbacks, `close()` once at the end.

    Args:
        path: the MCAP file (created).
        graph_text: the graph, stored in the `umad` metadata.
        extra_metadata: more of the `umad` metadata.
        views: add these views of every message (`LogViews`), made on a thread of their own; None: none.
        mask_sources: map channel (`op/output`) -> the masks channel that refined it, for the views.
    """

    def __init__(
        self,
        path: str | Path,
        graph_text: str = "",
        extra_metadata: dict[str, str] | None = None,
        views: type[LogViews] | None = None,
        mask_sources: dict[str, str] | None = None,
    ):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, compression=CompressionType.ZSTD if _has_zstd() else CompressionType.NONE)
        self._writer.start(profile="umad", library=f"umad {package_version()}")
        self._writer.add_metadata("umad", {"graph": graph_text, "version": package_version(), **(extra_metadata or {})})
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._lock = threading.Lock()
        self.count = 0
        self._viz_queue: queue.Queue | None = None
        if views is not None:  # views are made off the Zenoh callback thread
            self._viz_queue = queue.Queue(maxsize=256)
            self._viz_thread = threading.Thread(target=self._viz_worker, args=(views, mask_sources or {}), daemon=True)
            self._viz_thread.start()

    def write(self, key: str, payload: bytes) -> BusMessage | None:
        """Store one payload as it is; returns the message it decodes to (None for a command or a
        malformed payload, stored all the same)."""
        try:
            msg = decode(payload)
            seq, stamp = msg.seq, msg.stamp_ns
        except MessageError:
            msg, seq, stamp = None, 0, 0
        if msg is not None and self._viz_queue is not None and msg.arrays:
            self._viz_queue.put((key, msg))
        with self._lock:
            channel = self._channels.get(key)
            if channel is None:
                encoding = "json" if "/_ctl/" in key or "/_resend/" in key else "msgpack"
                channel = self._channels[key] = self._writer.register_channel(key, encoding, 0)
            self._writer.add_message(channel, log_time_of(stamp), bytes(payload), stamp, seq)
            self.count += 1
        return msg

    def write_json(self, topic: str, schema_name: str, schema: dict, obj: dict, stamp_ns: int) -> None:
        """A viewable message: JSON with a JSON schema (e.g. foxglove.CompressedImage)."""
        with self._lock:
            schema_id = self._schemas.get(schema_name)
            if schema_id is None:
                schema_id = self._schemas[schema_name] = self._writer.register_schema(
                    schema_name, "jsonschema", json.dumps(schema).encode()
                )
            channel = self._channels.get(topic)
            if channel is None:
                channel = self._channels[topic] = self._writer.register_channel(topic, "json", schema_id)
            self._writer.add_message(
                channel, log_time_of(stamp_ns), json.dumps(obj, separators=(",", ":")).encode(), stamp_ns, 0
            )

    def _viz_worker(self, views: type[LogViews], mask_sources: dict[str, str]) -> None:
        made = views(mask_sources)
        failed: set[str] = set()  # channels whose views failed: logged once each
        while True:
            item = self._viz_queue.get()
            if item is None:
                return
            key, msg = item
            _, _, rest = key.partition("/")  # drop "umad/"
            op_output = rest.partition("/")[2]
            try:
                for view in made.of(op_output, msg):
                    self.write_json(view.topic, view.schema, made.schema(view.schema), view.body, msg.stamp_ns)
            except Exception:  # a view is a convenience: the exact payload is recorded all the same
                if op_output not in failed:
                    failed.add(op_output)
                    log.exception(
                        "no view of %s %s#%d (later failures on it are not logged)",
                        op_output,
                        msg.run,
                        msg.seq,
                    )

    def close(
        self, drop_views: bool = False, metadata_name: str | None = None, metadata: dict[str, str] | None = None
    ) -> None:
        """Finish the file (readable from here on), with a last metadata record if given;
        `drop_views`: pictures not yet encoded are left out (a run stopped by a signal)."""
        if self._viz_queue is not None:
            while drop_views:
                try:
                    self._viz_queue.get_nowait()
                except queue.Empty:
                    break
            self._viz_queue.put(None)
            self._viz_thread.join()
        with self._lock:
            if metadata_name is not None:
                self._writer.add_metadata(metadata_name, metadata or {})
            self._writer.finish()
            self._file.close()


def _has_zstd() -> bool:
    try:
        import zstandard  # noqa: F401
    except ImportError:
        return False
    return True


@dataclass
class LogMessage:
    topic: str
    data: bytes
    log_time: int
    publish_time: int
    sequence: int


def read_log(path: str | Path, allow_truncated: bool = False) -> Iterator[LogMessage]:
    """Stream the bus messages of a log in file order.

    A truncated or corrupt file raises LogError saying how many messages were readable; with
    `allow_truncated=True` those messages are yielded and reading stops quietly at the break.
    """
    path = Path(path)
    if not path.is_file():
        raise LogError(f"{path}: log file not found")
    channels: dict[int, Channel] = {}
    count = 0
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message):
                    channel = channels.get(record.channel_id)
                    if channel is None or channel.message_encoding != "msgpack":
                        continue
                    count += 1
                    yield LogMessage(channel.topic, record.data, record.log_time, record.publish_time, record.sequence)
        except Exception as exc:  # the mcap parser raises many types on a broken file
            if allow_truncated:
                return
            raise LogError(
                f"{path}: log is truncated or corrupt after {count} readable messages ({type(exc).__name__}: {exc}); "
                "pass --allow-truncated to use those",
                readable=count,
            ) from None


def read_metadata(path: str | Path, name: str = "umad") -> dict[str, str]:
    """A metadata record of the log (`umad`: graph text, version; `umad_recording`: what the
    recorder lost), or {} if the log has none. The summary's index finds it without reading the
    messages; a log without one (truncated) is read from the start."""
    with open(path, "rb") as f:
        try:
            reader = make_reader(f)
            if reader.get_summary() is not None:
                return next((dict(m.metadata) for m in reader.iter_metadata() if m.name == name), {})
        except Exception:  # no summary (a truncated file): read the records in order
            pass
        if name == RECORDING_METADATA:  # written at the close, with the summary: an unclosed log has none
            return {}
        f.seek(0)
        try:
            for record in StreamReader(f).records:
                if isinstance(record, Metadata) and record.name == name:
                    return dict(record.metadata)
        except Exception:  # a truncated file may still carry its metadata; a missing record means none
            pass
    return {}


def recording_outcome(path: str | Path) -> dict | None:
    """What the recorder could not record: `{"lost": {channel: payloads}, "lacking": {channel:
    frames}, "stopped": bool}`; None for a log that does not say (closed by an older recorder, or
    not at all)."""
    record = read_metadata(path, RECORDING_METADATA)
    if not record:
        return None
    return {
        "lost": json.loads(record.get("lost") or "{}"),
        "lacking": json.loads(record.get("lacking") or "{}"),
        "stopped": json.loads(record.get("stopped") or "false"),
    }


def describe_loss(outcome: dict | None) -> str:
    """`lost 16 payloads (replayer/camera 8, ...); frames lacking: replayer/camera 16, ...`, or ''
    for a complete recording (or one that does not say)."""
    if not outcome:
        return ""
    short = lambda key: "/".join(key.split("/")[2:]) or key  # noqa: E731  umad/<graph>/op/out -> op/out
    parts = []
    if outcome.get("lost"):
        lost = outcome["lost"]
        detail = ", ".join(f"{short(k)} {n}" for k, n in sorted(lost.items()))
        parts.append(f"lost {sum(lost.values())} payloads ({detail})")
    if outcome.get("lacking"):
        parts.append("frames lacking: " + ", ".join(f"{short(k)} {n}" for k, n in sorted(outcome["lacking"].items())))
    return "; ".join(parts)
