"""Frames out of a recorded log: the messages the sweep needs, regrouped by `(run, seq)`.

A log (umad_common/dataflow/record/mcap_log.py) holds each bus message's exact payload on the channel `umad/<graph>/<op>/<output>`:

- `<replayer>/truth`    -> the anomaly labels (0/1/255) and the semantic tags;
- `<world_model>/frame` -> target and reconstruction (kept as uint8, for the overlay pictures);
- `<op>/map` with meta `metric` -> one normalised difference map per metric (aliases pd/td accepted),
  and the lidar map's `above_returns` mask (where the shipped fusion may weigh the camera maps down);
- `<segmenter>/masks`   -> (K, h, w) bool masks per segmenter operator (meta `method`), bit-packed;
- `<op>/map` with meta `model: mnad` (or op id `mnad`) -> the MNAD baseline's L2 map.

Everything else (camera, lidar, fused and refined maps, metrics, viz channels) is skipped undecoded.
A frame is complete once `lag` newer frames of its run have appeared (lossless delivery keeps frames
at most a window apart); a message arriving later is counted as late and dropped; a retransmitted
message is counted once.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from umad_common.dataflow.api.messages import MessageError, decode
from umad_common.dataflow.record.mcap_log import LogError, read_log
from umad_common.datasets.anovox import ANOMALY_TAGS
from umad_common.differences import ABOVE_RETURNS_ARRAY

METRIC_ALIASES = {"pd": "perceptual", "td": "temporal", "l1": "abs", "l2": "mse"}
WANTED_OUTPUTS = ("truth", "frame", "map", "masks")


def canonical_metric(name: str) -> str:
    return METRIC_ALIASES.get(name.lower(), name.lower())


@dataclass
class PackedMasks:
    """(K, h, w) bool masks at one bit per pixel while a frame waits in the buffer (8x smaller)."""

    bits: np.ndarray
    shape: tuple[int, int, int]

    @classmethod
    def pack(cls, masks: np.ndarray) -> PackedMasks:
        return cls(np.packbits(masks, axis=-1), tuple(masks.shape))

    def unpack(self) -> np.ndarray:
        return np.unpackbits(self.bits, axis=-1, count=self.shape[-1]).astype(bool)


@dataclass
class FrameRecord:
    """What the sweep needs of one frame; arrays are copies (the payloads are freed)."""

    run: str
    seq: int
    truth: np.ndarray | None = None  # (H, W) uint8 0/1/255
    target: np.ndarray | None = None  # (h, w, 3) uint8
    recon: np.ndarray | None = None  # (h, w, 3) uint8
    diffs: dict[str, np.ndarray] = field(default_factory=dict)  # canonical metric -> (h, w) float32
    above_lidar: np.ndarray | None = None  # (h, w) bool: the lidar map's `above_returns`, where it sent one
    masks: dict[str, PackedMasks] = field(default_factory=dict)  # segmenter op -> (K, h, w) bool, packed
    mnad: np.ndarray | None = None  # (h', w') float32
    anomaly_tags: tuple[int, ...] = ()  # semantic tags under the anomaly pixels (AnoVox categories)
    semantic: np.ndarray | None = None  # (H, W) uint8 CARLA tags, where the truth carries them


@dataclass
class LogStats:
    messages: int = 0  # bus messages read from the log
    decoded: int = 0  # of those, decoded because the sweep needs their output
    bad: int = 0  # payloads that failed to decode (counted, skipped)
    duplicates: int = 0  # retransmissions of a (channel, run, seq) already read
    late: int = 0  # messages of a frame already evaluated
    truncated: str | None = None  # why reading stopped early, if it did
    frames: int = 0  # (run, seq) groups formed
    segmenters: dict[str, str] = field(default_factory=dict)  # segmenter op -> method
    map_notes: dict[str, dict] = field(default_factory=dict)  # metric -> its maps' normalization, extractor


def _to_uint8(image: np.ndarray) -> np.ndarray:
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def frames_from_log(path: str | Path, stats: LogStats, lag: int = 32) -> Iterator[FrameRecord]:
    """Stream the log's frames, each once, after `lag` newer frames of its run have appeared (or at the end).

    Counting frames, not seq numbers, keeps this right when a run's seqs are sparse (every k-th frame).

    A truncated or corrupt log ends the stream at the last readable message; `stats.truncated` says why.
    """
    buffer: dict[tuple[str, int], FrameRecord] = {}
    seqs_seen: dict[str, list[int]] = {}  # run -> every seq seen, sorted
    done: set[tuple[str, int]] = set()
    seen: set[tuple[str, str, int]] = set()

    def ready(run: str, upto: int) -> Iterator[FrameRecord]:
        for key in sorted(k for k in buffer if k[0] == run and k[1] <= upto):
            done.add(key)
            stats.frames += 1
            yield buffer.pop(key)

    messages = read_log(path)
    while True:
        try:
            entry = next(messages)
        except StopIteration:
            break
        except LogError as exc:
            stats.truncated = str(exc)
            break
        except Exception as exc:  # a decompressor's own error type on a cut chunk: same meaning
            stats.truncated = (
                f"{path}: log is truncated or corrupt after {stats.messages} messages ({type(exc).__name__}: {exc})"
            )
            break
        stats.messages += 1
        parts = entry.topic.split("/")
        if len(parts) != 4 or parts[0] != "umad" or parts[2].startswith("_") or parts[3] not in WANTED_OUTPUTS:
            continue
        op, output = parts[2], parts[3]
        try:
            msg = decode(entry.data)
        except MessageError:
            stats.bad += 1
            continue
        stats.decoded += 1
        key = (msg.run, msg.seq)
        if (entry.topic, *key) in seen:
            stats.duplicates += 1
            continue
        seen.add((entry.topic, *key))
        if key in done:
            stats.late += 1
            continue
        record = buffer.setdefault(key, FrameRecord(msg.run, msg.seq))
        _fill(record, op, output, msg, stats)
        run_seqs = seqs_seen.setdefault(msg.run, [])
        position = bisect.bisect_left(run_seqs, msg.seq)
        if position == len(run_seqs) or run_seqs[position] != msg.seq:
            run_seqs.insert(position, msg.seq)
            if len(run_seqs) > lag:
                yield from ready(msg.run, run_seqs[-lag - 1])
    for run in sorted({k[0] for k in buffer}):
        yield from ready(run, max(k[1] for k in buffer if k[0] == run))


def _fill(record: FrameRecord, op: str, output: str, msg, stats: LogStats) -> None:
    arrays, meta = msg.arrays, msg.meta
    if output == "truth" and "anomaly" in arrays:
        record.truth = np.array(arrays["anomaly"], dtype=np.uint8)
        semantic = arrays.get("semantic")
        if semantic is not None and semantic.shape == record.truth.shape:
            record.semantic = np.array(semantic, dtype=np.uint8)
            found = np.unique(record.semantic[record.truth == 1])
            record.anomaly_tags = tuple(int(t) for t in found if int(t) in ANOMALY_TAGS)
    elif output == "frame" and "target" in arrays and "recon" in arrays:
        record.target, record.recon = _to_uint8(arrays["target"]), _to_uint8(arrays["recon"])
    elif output == "masks" and "masks" in arrays:
        record.masks[op] = PackedMasks.pack(np.asarray(arrays["masks"], dtype=bool))
        stats.segmenters.setdefault(op, str(meta.get("method", op)))
    elif output == "map" and "map" in arrays:
        if meta.get("no_data"):
            return  # a lidar map without returns: fusion left it out, so the sweep does too
        if "metric" in meta:
            metric = canonical_metric(str(meta["metric"]))
            record.diffs[metric] = np.array(arrays["map"], dtype=np.float32)
            if ABOVE_RETURNS_ARRAY in arrays:
                record.above_lidar = np.array(arrays[ABOVE_RETURNS_ARRAY], dtype=bool)
            stats.map_notes.setdefault(metric, {k: meta[k] for k in ("normalization", "extractor") if k in meta})
        elif meta.get("model") == "mnad" or op == "mnad":
            record.mnad = np.array(arrays["map"], dtype=np.float32)
