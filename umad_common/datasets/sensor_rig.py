"""The camera and the lidar of a drive: where they sit on the vehicle and how a lidar point lands in
the camera's image.

The replayer sends a drive's rig as the lidar message's meta `sensors`: an AnoVox scenario's
sensor_setup.json (`umad_common.datasets.anovox.read_sensor_setup`), or a recording's `/tf_static`
and camera info (`umad_common.datasets.recording.rig_from_transforms`), which add the camera's focal
lengths and centre (`focal`, `centre`, pixels) and each sensor's `axes` (3x3: its x, y, z axes as
columns in the vehicle's x forward, y left, z up). The `geometry` segmenter and the world model's
lidar view both project the cloud with it. Locations follow CARLA (x forward, y right, z up, metres);
clouds hold (x, -y, z, intensity) in the lidar's frame (x forward, y left, z up).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

Triplet = tuple[float, float, float]


class SensorSetupError(ValueError):
    """A sensor setup that cannot place the camera and the lidar: names what is missing or unsupported."""


Matrix = tuple[Triplet, Triplet, Triplet]


@dataclass(frozen=True)
class SensorRig:
    """A pinhole camera and a lidar, both mounted on the vehicle at `*_location` (CARLA axes, metres).

    The camera has the horizontal field of view `fov` degrees with square pixels and its principal
    point at the centre, unless `focal` (fx, fy) and `centre` (cx, cy) say otherwise (pixels at its own
    size). `camera_axes` and `lidar_axes` turn each sensor on the vehicle (columns: the sensor's x
    forward, y left, z up in the vehicle's); None: aligned with the vehicle."""

    width: int
    height: int
    fov: float
    camera_location: Triplet
    lidar_location: Triplet
    focal: tuple[float, float] | None = None
    centre: tuple[float, float] | None = None
    camera_axes: Matrix | None = None
    lidar_axes: Matrix | None = None

    @classmethod
    def anovox(cls) -> SensorRig:
        """AnoVox's rig: a 768 x 512 camera of FOV 90 and the lidar, both at (0, 0, 1.8)."""
        return cls(768, 512, 90.0, (0.0, 0.0, 1.8), (0.0, 0.0, 1.8))

    @classmethod
    def from_sensors(cls, sensors: dict, where: str) -> SensorRig:
        """From the replayer's `sensors` meta (see `umad_common.datasets.anovox.read_sensor_setup`).

        Raises:
            SensorSetupError: the setup lacks the camera or the lidar, or rotates either.
        """
        camera, lidar = sensors.get("camera"), sensors.get("lidar")
        if not camera or not lidar:
            raise SensorSetupError(f"{where}: sensor setup {sensors!r} lacks the camera or the lidar")
        for name, sensor in (("camera", camera), ("lidar", lidar)):
            if any(abs(float(a)) > 1e-6 for a in sensor.get("rotation", (0, 0, 0))):
                raise SensorSetupError(
                    f"{where}: {name} rotation {sensor['rotation']} is not supported; expected (0, 0, 0) as in "
                    "AnoVox, or the sensor's `axes` matrix"
                )

        def pair(value) -> tuple[float, float] | None:
            return None if value is None else (float(value[0]), float(value[1]))

        def axes(value) -> Matrix | None:
            if value is None:
                return None
            matrix = np.asarray(value, np.float64)
            if matrix.shape != (3, 3) or not np.allclose(matrix @ matrix.T, np.eye(3), atol=1e-6):
                raise SensorSetupError(f"{where}: axes {value!r}; expected a 3x3 rotation matrix")
            return None if np.array_equal(matrix, np.eye(3)) else tuple(tuple(float(v) for v in row) for row in matrix)

        return cls(
            int(camera["width"]),
            int(camera["height"]),
            float(camera["fov"]),
            tuple(float(v) for v in camera["location"]),
            tuple(float(v) for v in lidar["location"]),
            pair(camera.get("focal")),
            pair(camera.get("centre")),
            axes(camera.get("axes")),
            axes(lidar.get("axes")),
        )

    def project(self, points: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel (row, col) in an image of `shape` (h, w) (the camera resized without a crop) and depth
        along the camera's axis of every (x, -y, z) lidar point; depth <= 0 means behind the camera."""
        h, w = shape
        focal = self.width / 2 / np.tan(np.radians(self.fov) / 2)  # px at the camera's own size
        fx, fy = self.focal or (focal, focal)
        offset = np.subtract(self.lidar_location, self.camera_location)  # lidar origin seen from the camera
        if self.camera_axes is None and self.lidar_axes is None:
            forward = points[:, 0] + offset[0]
            right = -points[:, 1] + offset[1]
            up = points[:, 2] + offset[2]
        else:  # turn the points into the vehicle's axes, shift them to the camera, turn them into its axes
            xyz = np.asarray(points[:, :3], np.float64)
            if self.lidar_axes is not None:
                xyz = xyz @ np.asarray(self.lidar_axes).T
            xyz = xyz + offset * (1.0, -1.0, 1.0)
            if self.camera_axes is not None:
                xyz = xyz @ np.asarray(self.camera_axes)
            forward, right, up = xyz[:, 0], -xyz[:, 1], xyz[:, 2]
        safe = np.where(forward > 1e-6, forward, np.inf)
        if self.centre is None:
            col = w / 2 + fx * (w / self.width) * right / safe
            row = h / 2 - fy * (h / self.height) * up / safe
        else:
            col = self.centre[0] * (w / self.width) + fx * (w / self.width) * right / safe
            row = self.centre[1] * (h / self.height) - fy * (h / self.height) * up / safe
        return np.floor(row).astype(np.int64), np.floor(col).astype(np.int64), forward
