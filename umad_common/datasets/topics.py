"""Which topic of a recording plays which role: by name (`--topics camera=/a,lidar=/b`) or by type.

Roles and the message types each takes:

| role | types |
|---|---|
| camera (required; the clock) | sensor_msgs/Image, sensor_msgs/CompressedImage, foxglove.RawImage, foxglove.CompressedImage |
| lidar | sensor_msgs/PointCloud2, foxglove.PointCloud |
| odometry | nav_msgs/Odometry, foxglove.PoseInFrame |
| control | carla_msgs/CarlaEgoVehicleControl, ackermann_msgs/AckermannDriveStamped |
| labels (evaluation only) | an image topic, mono8, nonzero = anomaly |
| camera_info | sensor_msgs/CameraInfo, foxglove.CameraCalibration |
| tf | tf2_msgs/TFMessage on `/tf_static`, foxglove.FrameTransform(s) |

A role named in `--topics` takes that topic. Otherwise a role is chosen where exactly one topic has
its type. Image topics are told apart by name: one whose name says labels (`label`, `anomal`, `truth`,
`mask`) is the labels candidate, never the camera's. Two candidates for the camera, the lidar, the
odometry or the control is an error that lists them and says how to pick; the camera info nearest the
camera's namespace is taken among several.
"""

from __future__ import annotations

from dataclasses import dataclass

from umad_common.datasets.drive import DatasetError
from umad_common.datasets.recording_messages import (
    CAMERA_INFO_TYPES,
    CLOUD_TYPES,
    CONTROL_TYPES,
    IMAGE_TYPES,
    ODOMETRY_TYPES,
    TRANSFORM_TYPES,
)

ROLE_TYPES = {
    "camera": IMAGE_TYPES,
    "lidar": CLOUD_TYPES,
    "odometry": ODOMETRY_TYPES,
    "control": CONTROL_TYPES,
    "labels": IMAGE_TYPES,
    "camera_info": CAMERA_INFO_TYPES,
    "tf": TRANSFORM_TYPES,
}
LABEL_NAME_HINTS = ("label", "anomal", "truth", "mask")
EXCLUSIVE_ROLES = ("camera", "lidar", "odometry", "control")  # two candidates: an error, not a guess
TOPICS_SYNTAX = "--topics camera=/a,lidar=/b,odometry=/c,control=/d,labels=/e"


@dataclass(frozen=True)
class Choice:
    """The topic a role reads and why it was chosen."""

    topic: str
    type: str
    why: str


def parse_topics(text: str | dict[str, str] | None) -> dict[str, str]:
    """`camera=/a,lidar=/b` -> {"camera": "/a", "lidar": "/b"}; DatasetError naming a bad item."""
    if text is None or isinstance(text, dict):
        chosen = dict(text or {})
    else:
        chosen = {}
        for item in (part.strip() for part in text.split(",")):
            role, sep, topic = item.partition("=")
            if not item:
                continue
            if not sep or not topic.strip():
                raise DatasetError(f"--topics item {item!r}: expected role=/topic, as in {TOPICS_SYNTAX}")
            if role.strip() in chosen:
                raise DatasetError(f"--topics names the role {role.strip()!r} twice; expected each role once")
            chosen[role.strip()] = topic.strip()
    unknown = sorted(set(chosen) - set(ROLE_TYPES))
    if unknown:
        raise DatasetError(f"--topics roles {unknown} are unknown; expected roles among {', '.join(ROLE_TYPES)}")
    return chosen


def listing(topics: dict[str, str], names) -> str:
    return "; ".join(f"{name} ({topics[name]})" for name in names)


def choose_topics(
    topics: dict[str, str], named: dict[str, str], where: str, wanted: set[str] | None = None
) -> dict[str, list[Choice]]:
    """Each role's topics (one, or several for `tf`; absent: the recording has none) in a recording
    whose topics have these types.

    Args:
        topics: topic -> canonical type (`umad_common.datasets.recording_messages.canonical_type`).
        named: role -> topic, from `--topics`.
        where: the recording, for messages.
        wanted: the roles to choose (the camera always); None: all. A role not wanted is not chosen
            by type, so its candidates cannot be ambiguous (a reader of the camera alone).

    Raises:
        DatasetError: a named topic the recording lacks or whose type the role cannot take; no camera;
            two candidates for a role in EXCLUSIVE_ROLES.
    """
    wanted = set(ROLE_TYPES) if wanted is None else {"camera", *wanted}
    chosen: dict[str, list[Choice]] = {}
    for role, topic in named.items():
        if topic not in topics:
            raise DatasetError(
                f"{where}: --topics {role}={topic}: no such topic; the recording has {listing(topics, sorted(topics))}"
            )
        if topics[topic] not in ROLE_TYPES[role]:
            raise DatasetError(
                f"{where}: --topics {role}={topic} has type {topics[topic]}; the {role} role takes "
                f"{', '.join(ROLE_TYPES[role])}"
            )
        chosen[role] = [Choice(topic, topics[topic], "named in --topics")]
    taken = {choice.topic for choices in chosen.values() for choice in choices}
    free = {topic: kind for topic, kind in topics.items() if topic not in taken}
    images = [t for t, kind in free.items() if kind in IMAGE_TYPES]
    hinted = [t for t in images if any(hint in t.lower() for hint in LABEL_NAME_HINTS)]
    if "labels" not in chosen and "labels" in wanted and len(hinted) == 1:
        chosen["labels"] = [Choice(hinted[0], free[hinted[0]], "its name says labels")]
    for role in ("camera", "lidar", "odometry", "control"):
        if role in chosen or role not in wanted:
            continue
        candidates = [t for t, kind in free.items() if kind in ROLE_TYPES[role]]
        if role == "camera":
            candidates = [t for t in candidates if t not in hinted]
        if len(candidates) == 1:
            chosen[role] = [Choice(candidates[0], free[candidates[0]], f"the only {role} type")]
        elif len(candidates) > 1:
            raise DatasetError(
                f"{where}: {len(candidates)} topics could be the {role}: {listing(topics, candidates)}; "
                f"pick one with --topics {role}=TOPIC"
            )
    if "camera" not in chosen:
        kinds = ", ".join(IMAGE_TYPES)
        raise DatasetError(
            f"{where}: no camera topic (types {kinds}) among {listing(topics, sorted(topics)) or 'no topics'}; "
            f"expected one, or name it with --topics camera=TOPIC"
        )
    if "camera_info" not in chosen and "camera_info" in wanted:
        infos = [t for t, kind in free.items() if kind in CAMERA_INFO_TYPES]
        if infos:
            camera = chosen["camera"][0].topic
            best = max(infos, key=lambda t: (common_prefix(t, camera), -len(t)))
            why = "the only camera info type" if len(infos) == 1 else "the camera info nearest the camera's topic"
            chosen["camera_info"] = [Choice(best, free[best], why)]
    if "tf" not in chosen and "tf" in wanted:
        static = [
            t
            for t, kind in free.items()
            if kind in TRANSFORM_TYPES and (kind != "tf2_msgs/msg/TFMessage" or t.rstrip("/").endswith("tf_static"))
        ]
        chosen["tf"] = [Choice(t, free[t], "transform type") for t in static]
        if not chosen["tf"]:
            del chosen["tf"]
    return chosen


def common_prefix(a: str, b: str) -> int:
    """How many leading `/`-separated name parts two topics share."""
    count = 0
    for x, y in zip(a.strip("/").split("/"), b.strip("/").split("/"), strict=False):
        if x != y:
            break
        count += 1
    return count
