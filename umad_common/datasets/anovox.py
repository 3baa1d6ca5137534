"""AnoVox scenarios on disk (one `Drive` format): a reader for both layouts and writers, as described
in ANOVOX.md.

Generator layout (the AnoVox generator's output; also what `umad generate synthetic` writes)::

    Scenario_<uuid>/sensor_setup.json
    Scenario_<uuid>/RGB-CAM(0, 0, 1.8)(0, 0, 0)_<hash>/RGB-CAM(0, 0, 1.8)(0, 0, 0)_<hash>_<frame>.png
    ... DEPTH_CAM, SEMANTIC-CAM, INSTANCE-CAM, LIDAR (.npy), ACTION/ACTION_<frame>.csv,
    ANOMALY/ANOMALY_<frame>.csv, ROUTE_MAP/ROUTE_MAP_<frame>.png

Benchmark layout (the released dataset)::

    Scenario_<uuid>/{RGB_IMG, SEMANTIC_IMG, DEPTH_IMG, PCD, ...}/<TYPE>_<frame>.<ext>

A folder is read as it is. A sensor folder that is absent gives `None` for that modality; a folder
that is present but lacks one frame's file, or a file that cannot be decoded, raises DatasetError
naming the file.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from umad_common.datasets.drive import DatasetError, Drive, DriveFrame, EgoState

ANOMALY_TAGS = (29, 30, 31, 32, 33, 34, 100)
ANOMALY_CATEGORIES = {
    29: "home",
    30: "animal",
    31: "nature",
    32: "special",
    33: "airplane",
    34: "falling",
    100: "anomaly",
}
GENERIC_ANOMALY_TAG = 100
EGO_VEHICLE_TAG = 214
# CARLA 0.9.14 semantic tag names (ANOVOX.md); every anomaly tag is named "anomaly".
CLASS_NAMES = {
    0: "unlabeled", 1: "road", 2: "sidewalk", 3: "building", 4: "wall", 5: "fence", 6: "pole", 7: "traffic light",
    8: "traffic sign", 9: "vegetation", 10: "terrain", 11: "sky", 12: "pedestrian", 13: "rider", 14: "car",
    15: "truck", 16: "bus", 17: "train", 18: "motorcycle", 19: "bicycle", 20: "static", 21: "dynamic", 22: "other",
    23: "water", 24: "road line", 25: "ground", 26: "bridge", 27: "rail track", 28: "guard rail",
    **{tag: "anomaly" for tag in ANOMALY_TAGS}, EGO_VEHICLE_TAG: "ego vehicle",
}  # fmt: skip


def class_name(tag: int) -> str:
    """The dataset's name of a semantic tag (`tag <n>` for one CARLA does not name)."""
    return CLASS_NAMES.get(int(tag), f"tag {int(tag)}")


ANOMALY_COLOUR = (245, 0, 0)  # benchmark SEMANTIC_IMG colour of every anomaly pixel
DEPTH_SCALE = 1000.0 / (2**24 - 1)  # CARLA raw depth: metres per unit of R + 256 G + 65536 B
KMH_PER_MPS = 3.6
RECORDING_PERIOD_NS = 100_000_000  # AnoVox and the synthetic world record at 10 Hz

# CARLA 0.9.14 CityScapes palette (RGB) by semantic tag.
CARLA_PALETTE = {
    0: (0, 0, 0), 1: (128, 64, 128), 2: (244, 35, 232), 3: (70, 70, 70), 4: (102, 102, 156), 5: (190, 153, 153),
    6: (153, 153, 153), 7: (250, 170, 30), 8: (220, 220, 0), 9: (107, 142, 35), 10: (152, 251, 152),
    11: (70, 130, 180), 12: (220, 20, 60), 13: (255, 0, 0), 14: (0, 0, 142), 15: (0, 0, 70), 16: (0, 60, 100),
    17: (0, 80, 100), 18: (0, 0, 230), 19: (119, 11, 32), 20: (110, 190, 160), 21: (170, 120, 50),
    22: (55, 90, 80), 23: (45, 60, 150), 24: (157, 234, 50), 25: (81, 0, 81), 26: (150, 100, 100),
    27: (230, 150, 140), 28: (180, 165, 180),
}  # fmt: skip

_FRAME_NUMBER = re.compile(r"_(\d+)\.[A-Za-z0-9]+$")
_GENERATOR_SENSORS = {  # modality -> accepted folder-name prefixes
    "rgb": ("RGB-CAM", "RGB_CAM"),
    "depth": ("DEPTH_CAM", "DEPTH-CAM"),
    "semantic": ("SEMANTIC-CAM", "SEMANTIC_CAM"),
    "instance": ("INSTANCE-CAM", "INSTANCE_CAM"),
    "lidar": ("LIDAR",),
    "action": ("ACTION",),
    "route": ("ROUTE_MAP",),
}
_BENCHMARK_SENSORS = {"rgb": "RGB_IMG", "depth": "DEPTH_IMG", "semantic": "SEMANTIC_IMG", "lidar": "PCD"}


def is_scenario_dir(path: Path) -> bool:
    """A Scenario_* folder that holds a camera folder of either layout."""
    if not (path.is_dir() and path.name.startswith("Scenario_")):
        return False
    return any(
        p.is_dir() and (p.name == "RGB_IMG" or p.name.startswith(_GENERATOR_SENSORS["rgb"])) for p in path.iterdir()
    )


def frame_number(path: Path) -> int | None:
    match = _FRAME_NUMBER.search(path.name)
    return int(match.group(1)) if match else None


def _index_folder(folder: Path) -> dict[int, Path]:
    """frame id -> file for every file in the folder whose name ends in _<frame>.<ext>."""
    files = {}
    for p in folder.iterdir():
        n = frame_number(p)
        if n is not None and p.is_file():
            files[n] = p
    return files


def read_png(path: Path, channels: tuple[int, ...], what: str) -> np.ndarray:
    """cv2 image as stored (BGR order for colour), checked for existence, decodability, channel count."""
    if not path.is_file():
        raise DatasetError(f"{path}: file is missing; expected {what}")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f"{path}: cannot be decoded; expected {what}")
    n = 1 if image.ndim == 2 else image.shape[2]
    if n not in channels or image.dtype != np.uint8:
        raise DatasetError(f"{path}: has {n} channel(s) of {image.dtype}; expected {what}")
    return image


def decode_depth(bgr: np.ndarray) -> np.ndarray:
    """CARLA raw depth PNG (as loaded by cv2, BGR) -> metres."""
    b, g, r = (bgr[..., k].astype(np.float64) for k in range(3))
    return ((r + 256.0 * g + 65536.0 * b) * DEPTH_SCALE).astype(np.float32)


def encode_depth(depth_m: np.ndarray) -> np.ndarray:
    """Metres -> CARLA raw depth as a BGR uint8 image for cv2.imwrite (clipped to 0..1000 m)."""
    units = np.round(np.clip(depth_m, 0, 1000.0) / DEPTH_SCALE).astype(np.int64)
    return np.stack([(units >> 16) & 255, (units >> 8) & 255, units & 255], axis=-1).astype(np.uint8)


def read_key_values(path: Path) -> dict[str, str]:
    """AnoVox `key ; value` csv -> dict (values as stripped strings)."""
    if not path.is_file():
        raise DatasetError(f"{path}: file is missing; expected `key ; value` lines")
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot be read as text ({exc}); expected `key ; value` lines") from None
    values = {}
    for line in lines:
        if line.strip():
            key, sep, value = line.partition(";")
            if not sep:
                raise DatasetError(f"{path}: line {line!r} has no ';'; expected `key ; value` lines")
            values[key.strip()] = value.strip()
    return values


def write_key_values(path: Path, values: dict[str, object]) -> None:
    path.write_text("".join(f"{key} ; {value}\n" for key, value in values.items()), encoding="utf-8")


def read_ego(path: Path) -> EgoState:
    """ACTION csv -> EgoState, by key; speed converted from km/h to m/s."""
    values = read_key_values(path)
    out = {}
    for key in ("speed", "throttle", "brake", "steer"):
        if key not in values:
            raise DatasetError(f"{path}: no {key!r} line; expected keys speed (km/h), throttle, brake, steer")
        try:
            out[key] = float(values[key])
        except ValueError:
            raise DatasetError(f"{path}: {key} = {values[key]!r} is not a number") from None
    return EgoState(out["speed"] / KMH_PER_MPS, out["throttle"], out["brake"], out["steer"])


def read_npy_cloud(path: Path) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(f"{path}: file is missing; expected a float32 [N, 4] lidar .npy")
    try:
        cloud = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot be loaded ({exc}); expected a float32 [N, 4] lidar .npy") from None
    if cloud.ndim != 2 or cloud.shape[1] < 4:
        raise DatasetError(f"{path}: lidar array has shape {cloud.shape}; expected [N, 4] (x, -y, z, intensity)")
    return np.ascontiguousarray(cloud[:, :4], dtype=np.float32)


_PCD_TYPES = {
    ("F", 4): "<f4",
    ("F", 8): "<f8",
    ("U", 1): "u1",
    ("U", 2): "<u2",
    ("U", 4): "<u4",
    ("I", 1): "i1",
    ("I", 2): "<i2",
    ("I", 4): "<i4",
}


def read_pcd(path: Path) -> np.ndarray:
    """ASCII or binary PCD -> (N, 4) float32 (x, y, z, intensity; intensity 0 if absent)."""
    if not path.is_file():
        raise DatasetError(f"{path}: file is missing; expected a PCD point cloud")
    raw = path.read_bytes()
    header, fields, sizes, types, counts, points, fmt, offset = {}, [], [], [], [], None, None, 0
    try:
        while fmt is None:
            end = raw.index(b"\n", offset)
            line = raw[offset:end].decode("ascii").strip()
            offset = end + 1
            if not line or line.startswith("#"):
                continue
            key, *rest = line.split()
            header[key.upper()] = rest
            if key.upper() == "DATA":
                fmt = rest[0].lower()
        fields, sizes = header["FIELDS"], [int(v) for v in header["SIZE"]]
        types, counts = header["TYPE"], [int(v) for v in header.get("COUNT", ["1"] * len(fields))]
        points = int(header["POINTS"][0])
        dtype = np.dtype(
            [(f, _PCD_TYPES[(t, s)], (c,)) for f, s, t, c in zip(fields, sizes, types, counts, strict=True)]
        )
    except (ValueError, KeyError, UnicodeDecodeError, IndexError) as exc:
        raise DatasetError(
            f"{path}: malformed PCD header ({type(exc).__name__}: {exc}); expected FIELDS/SIZE/TYPE/POINTS/DATA"
        ) from None
    if "x" not in fields or "y" not in fields or "z" not in fields:
        raise DatasetError(f"{path}: PCD fields {fields}; expected x, y, z (and intensity)")
    if fmt == "binary":
        if len(raw) - offset < points * dtype.itemsize:
            raise DatasetError(
                f"{path}: binary PCD holds {len(raw) - offset} data bytes; expected {points * dtype.itemsize}"
            )
        data = np.frombuffer(raw, dtype, count=points, offset=offset)
        cols = [data[f][:, 0].astype(np.float32) for f in ("x", "y", "z")]
    elif fmt == "ascii":
        try:
            table = np.loadtxt(raw[offset:].decode("ascii").splitlines(), dtype=np.float64, ndmin=2)
        except ValueError as exc:
            raise DatasetError(f"{path}: ASCII PCD data unreadable ({exc})") from None
        if table.shape[0] != points:
            raise DatasetError(f"{path}: ASCII PCD has {table.shape[0]} rows; expected POINTS {points}")
        starts = np.cumsum([0] + counts)
        data = {f: table[:, starts[k]] for k, f in enumerate(fields)}
        cols = [data[f].astype(np.float32) for f in ("x", "y", "z")]
    else:
        raise DatasetError(f"{path}: PCD DATA {fmt!r} is not supported; expected ascii or binary")
    name = "intensity" if "intensity" in fields else ("i" if "i" in fields else None)
    if name is None:
        intensity = np.zeros(points, np.float32)
    else:
        intensity = (data[name][:, 0] if fmt == "binary" else data[name]).astype(np.float32)
    return np.stack(cols + [intensity], axis=1)


def write_pcd(path: Path, cloud: np.ndarray, binary: bool = True) -> None:
    """(N, 4) float32 cloud -> PCD with fields x y z intensity (binary: bit-exact)."""
    cloud = np.ascontiguousarray(cloud[:, :4], dtype="<f4")
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\n"
        f"TYPE F F F F\nCOUNT 1 1 1 1\nWIDTH {len(cloud)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(cloud)}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    )
    body = (
        cloud.tobytes() if binary else "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in cloud).encode()
    )
    path.write_bytes(header.encode("ascii") + body)


def _triplet(value: object, path: Path, what: str) -> list[float]:
    """A sensor_setup.json location or rotation: [x, y, z], {"x", "y", "z"} or "(x, y, z)"."""
    if isinstance(value, dict):
        value = (
            [value.get(k) for k in ("x", "y", "z")]
            if "x" in value
            else [value.get(k) for k in ("pitch", "yaw", "roll")]
        )
    elif isinstance(value, str):
        value = value.strip("()[] ").split(",")
    try:
        numbers = [float(v) for v in value]  # type: ignore[union-attr]
    except (TypeError, ValueError):
        numbers = []
    if len(numbers) != 3:
        raise DatasetError(f"{path}: {what} is {value!r}; expected three numbers [x, y, z]")
    return numbers


def read_sensor_setup(path: Path) -> dict | None:
    """The camera and lidar of a generator-layout `sensor_setup.json`, or None if the file is absent:
    `{"camera": {"width", "height", "fov", "location", "rotation"}, "lidar": {"location", "rotation"}}`
    (CARLA axes: x forward, y right, z up, metres; rotations in degrees). The lidar entry is absent
    when the setup has no lidar."""
    if not path.is_file():
        return None
    try:
        setup = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: cannot be read as JSON ({exc}); expected the AnoVox sensor setup") from None
    by_type = (
        {s.get("sensor_type"): s for s in setup.values() if isinstance(s, dict)} if isinstance(setup, dict) else {}
    )
    camera = by_type.get("sensor.camera.rgb")
    if camera is None:
        raise DatasetError(f"{path}: no sensor with sensor_type 'sensor.camera.rgb'; expected the AnoVox sensor setup")
    args = camera.get("args", {})
    try:
        intrinsics = {
            "width": int(args["image_size_x"]),
            "height": int(args["image_size_y"]),
            "fov": float(args["fov"]),
        }
    except (KeyError, TypeError, ValueError):
        raise DatasetError(f"{path}: camera args {args!r}; expected image_size_x, image_size_y and fov") from None
    sensors = {
        "camera": {
            **intrinsics,
            "location": _triplet(camera.get("location"), path, "camera location"),
            "rotation": _triplet(camera.get("rotation", [0, 0, 0]), path, "camera rotation"),
        }
    }
    lidar = by_type.get("sensor.lidar.ray_cast")
    if lidar is not None:
        sensors["lidar"] = {
            "location": _triplet(lidar.get("location"), path, "lidar location"),
            "rotation": _triplet(lidar.get("rotation", [0, 0, 0]), path, "lidar rotation"),
        }
    return sensors


def scenario_weathers(source: str | Path) -> dict[str, str]:
    """Scenario folder name (`Scenario_<id>`) -> the weather preset the data's scenario config files
    name for it (`Scenario_Configuration_Files/scenario_config_map_*.json`, entries with a
    `scenario_id` and a string `weather`, as `umad generate synthetic` writes them).

    The config folder is looked for in `source` (a data folder, a split folder or one scenario) and
    up to three folders above it. Data without such files, or entries without a weather, give no
    entry: a reader shows those drives' weather as unknown.
    """
    source = Path(source)
    weathers: dict[str, str] = {}
    for folder in [source, *list(source.parents)[:3]]:
        for config in sorted((folder / "Scenario_Configuration_Files").glob("scenario_config_map_*.json")):
            try:
                data = json.loads(config.read_text())
            except (OSError, ValueError):
                continue
            entries = data.get("scenarios", []) if isinstance(data, dict) else data
            for entry in entries if isinstance(entries, list) else []:
                if isinstance(entry, dict) and isinstance(entry.get("weather"), str) and "scenario_id" in entry:
                    weathers.setdefault(f"Scenario_{entry['scenario_id']}", entry["weather"])
    return weathers


def semantic_to_colour(semantic: np.ndarray) -> np.ndarray:
    """CARLA tags -> RGB palette image; every anomaly tag becomes ANOMALY_COLOUR."""
    lut = np.zeros((256, 3), np.uint8)
    for tag, colour in CARLA_PALETTE.items():
        lut[tag] = colour
    lut[list(ANOMALY_TAGS)] = ANOMALY_COLOUR
    return lut[semantic]


def colour_to_semantic(rgb: np.ndarray) -> np.ndarray:
    """RGB palette image -> CARLA tags (anomaly colour -> 100, unknown colours -> 0)."""
    key = (rgb[..., 0].astype(np.int64) << 16) | (rgb[..., 1].astype(np.int64) << 8) | rgb[..., 2]
    table = {(r << 16) | (g << 8) | b: tag for tag, (r, g, b) in CARLA_PALETTE.items()}
    r, g, b = ANOMALY_COLOUR
    table[(r << 16) | (g << 8) | b] = GENERIC_ANOMALY_TAG
    values, inverse = np.unique(key, return_inverse=True)
    tags = np.array([table.get(int(v), 0) for v in values], np.uint8)
    return tags[inverse].reshape(key.shape)


class AnoVoxScenario(Drive):
    """One scenario folder of either layout; frames load lazily by index.

    Args:
        path: the Scenario_* folder.
        every: keep every k-th frame (k >= 1), counted in the sorted frame ids.
        keep: read only these modalities (folder keys: rgb, lidar, action, route, depth, semantic,
            instance); None: all. The others come back as None (the anomaly as zeros).
    """

    def __init__(self, path: str | Path, every: int = 1, keep: tuple[str, ...] | None = None):
        self.path = Path(path)
        if every < 1:
            raise ValueError(f"every must be >= 1, got {every}")
        if not self.path.is_dir():
            raise DatasetError(f"{self.path}: no such scenario folder")
        self.name = self.path.name
        subdirs = {p.name: p for p in self.path.iterdir() if p.is_dir()}
        self.folders: dict[str, Path] = {}
        if "RGB_IMG" in subdirs:
            self.layout = "benchmark"
            self.folders = {key: subdirs[name] for key, name in _BENCHMARK_SENSORS.items() if name in subdirs}
        else:
            self.layout = "generator"
            for key, prefixes in _GENERATOR_SENSORS.items():
                matches = sorted(n for n in subdirs if n.startswith(prefixes))
                if matches:
                    self.folders[key] = subdirs[matches[0]]
        if keep is not None:
            self.folders = {key: folder for key, folder in self.folders.items() if key in keep or key == "rgb"}
        if "rgb" not in self.folders:
            raise DatasetError(
                f"{self.path}: no camera folder; expected RGB_IMG/ (benchmark layout) or RGB-CAM(...)_<hash>/ (generator layout)"
            )
        self._files = {key: _index_folder(folder) for key, folder in self.folders.items()}
        # Every frame any sensor recorded: a frame whose camera image is missing is then reported
        # when it is read, instead of silently leaving a gap in the drive.
        all_ids = sorted(set(self._files["rgb"]).union(*(ids for key, ids in self._files.items() if key != "rgb")))
        if not self._files["rgb"]:
            raise DatasetError(f"{self.folders['rgb']}: no image files named *_<frame>.png")
        self.every = every
        self.frame_ids: list[int] = all_ids[::every]
        self.sensors = read_sensor_setup(self.path / "sensor_setup.json")  # None in the benchmark layout
        self.modalities = frozenset(self.folders) | ({"anomaly"} if "semantic" in self.folders else set())

    def __len__(self) -> int:
        return len(self.frame_ids)

    def __repr__(self) -> str:
        return f"AnoVoxScenario({str(self.path)!r}, layout={self.layout!r}, frames={len(self)}, every={self.every})"

    def _file(self, key: str, frame_id: int) -> Path | None:
        """The file of one modality for a frame; None if the modality's folder is absent."""
        if key not in self.folders:
            return None
        path = self._files[key].get(frame_id)
        if path is None:
            raise DatasetError(
                f"{self.folders[key]}: no file for frame {frame_id}; expected a file named *_{frame_id}.<ext> like the other frames"
            )
        return path

    def stamp_ns(self, index: int) -> int:
        """AnoVox records at 10 Hz: frame index x `every` x 100 ms (so sampling keeps real time)."""
        return self.check_index(index) * self.every * RECORDING_PERIOD_NS

    def describe(self) -> str:
        return f"AnoVox folder, {self.layout} layout"

    def notes(self) -> list[str]:
        missing = [key for key in ("lidar", "action", "semantic") if key not in self.folders]
        return [f"no {key} folder" for key in missing] + ([] if self.sensors else ["no sensor_setup.json"])

    def __getitem__(self, index: int) -> DriveFrame:
        frame_id = self.frame_ids[self.check_index(index)]
        rgb_path = self._file("rgb", frame_id)
        rgb = read_png(rgb_path, (3, 4), "an 8-bit RGB PNG")[..., 2::-1].copy()
        shape = rgb.shape[:2]

        def same_shape(array: np.ndarray, path: Path) -> np.ndarray:
            if array.shape[:2] != shape:
                raise DatasetError(
                    f"{path}: image is {array.shape[1]}x{array.shape[0]}; expected {shape[1]}x{shape[0]} like the RGB image"
                )
            return array

        depth = semantic = instance = lidar = route = None
        if (path := self._file("depth", frame_id)) is not None:
            depth = same_shape(decode_depth(read_png(path, (3, 4), "a CARLA raw depth PNG (RGB)")), path)
        anomaly = np.zeros(shape, np.uint8)
        if (path := self._file("semantic", frame_id)) is not None:
            if self.layout == "benchmark":
                colour = read_png(path, (3, 4), "an RGB palette-coded semantic PNG")[..., 2::-1]
                semantic = same_shape(colour_to_semantic(colour), path)
                anomaly = np.all(colour == ANOMALY_COLOUR, axis=-1).astype(np.uint8)
            else:
                image = read_png(path, (1, 3, 4), "a semantic PNG of CARLA tags")
                semantic = same_shape(image if image.ndim == 2 else image[..., 2].copy(), path)
                anomaly = np.isin(semantic, ANOMALY_TAGS).astype(np.uint8)
        if (path := self._file("instance", frame_id)) is not None:
            image = read_png(path, (1, 3, 4), "an instance PNG (R = tag, G, B = object id)")
            ids = (
                image.astype(np.int32)
                if image.ndim == 2
                else image[..., 1].astype(np.int32) + 256 * image[..., 0].astype(np.int32)
            )
            instance = same_shape(ids, path)
        if (path := self._file("lidar", frame_id)) is not None:
            lidar = read_pcd(path) if self.layout == "benchmark" else read_npy_cloud(path)
        ego = EgoState()
        if (path := self._file("action", frame_id)) is not None:
            ego = read_ego(path)
        if (path := self._file("route", frame_id)) is not None:
            route = read_png(path, (1, 3, 4), "a 192x192 grayscale route PNG")
            route = route if route.ndim == 2 else route[..., 0].copy()
        return DriveFrame(frame_id, rgb, depth, semantic, instance, anomaly, lidar, ego, route)


def write_benchmark_scenario(
    frames: Iterable[DriveFrame], out_root: str | Path, name: str, binary_pcd: bool = True
) -> Path:
    """Write frames in the benchmark layout: RGB_IMG, SEMANTIC_IMG (palette colours, anomalies
    (245, 0, 0)), DEPTH_IMG (CARLA raw encoding) and PCD (x y z intensity) where the frame has them.

    Returns:
        The new Scenario folder `out_root/name`.
    """
    if not name.startswith("Scenario_"):
        raise ValueError(f"scenario name {name!r} must start with 'Scenario_'")
    root = Path(out_root) / name
    for frame in frames:
        fid = frame.frame_id
        targets = {
            "RGB_IMG": frame.rgb is not None,
            "SEMANTIC_IMG": frame.semantic is not None,
            "DEPTH_IMG": frame.depth is not None,
            "PCD": frame.lidar is not None,
        }
        for folder, present in targets.items():
            if present:
                (root / folder).mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / "RGB_IMG" / f"RGB_IMG_{fid}.png"), frame.rgb[..., ::-1])
        if frame.semantic is not None:
            colour = semantic_to_colour(frame.semantic)
            colour[frame.anomaly.astype(bool)] = ANOMALY_COLOUR
            cv2.imwrite(str(root / "SEMANTIC_IMG" / f"SEMANTIC_IMG_{fid}.png"), colour[..., ::-1])
        if frame.depth is not None:
            cv2.imwrite(str(root / "DEPTH_IMG" / f"DEPTH_IMG_{fid}.png"), encode_depth(frame.depth))
        if frame.lidar is not None:
            write_pcd(root / "PCD" / f"PCD_{fid}.pcd", frame.lidar, binary=binary_pcd)
    return root
