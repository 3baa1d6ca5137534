"""The camera and the lidar of a drive: where they sit on the vehicle and how a lidar point lands in
the camera's image.

The replayer sends a scenario's sensor_setup.json (`umad_common.datasets.anovox.read_sensor_setup`)
as the lidar message's meta `sensors`; the `geometry` segmenter and the world model's lidar view
both project the cloud with it. Axes follow CARLA (x forward, y right, z up, metres); AnoVox clouds
store (x, -y, z, intensity) in the lidar's frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

Triplet = tuple[float, float, float]


class SensorSetupError(ValueError):
    """A sensor setup that cannot place the camera and the lidar: names what is missing or unsupported."""


@dataclass(frozen=True)
class SensorRig:
    """A pinhole camera (principal point at the centre, horizontal field of view `fov` degrees, square
    pixels) and a lidar, both mounted on the vehicle at `*_location` (CARLA axes, metres)."""

    width: int
    height: int
    fov: float
    camera_location: Triplet
    lidar_location: Triplet

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
                    f"{where}: {name} rotation {sensor['rotation']} is not supported; expected (0, 0, 0) as in AnoVox"
                )
        return cls(
            int(camera["width"]),
            int(camera["height"]),
            float(camera["fov"]),
            tuple(float(v) for v in camera["location"]),
            tuple(float(v) for v in lidar["location"]),
        )

    def project(self, points: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel (row, col) in an image of `shape` (h, w) (the camera resized without a crop) and depth
        along the camera's axis of every (x, -y, z) lidar point; depth <= 0 means behind the camera."""
        h, w = shape
        focal = self.width / 2 / np.tan(np.radians(self.fov) / 2)  # px at the camera's own size
        offset = np.subtract(self.lidar_location, self.camera_location)  # lidar origin seen from the camera
        forward = points[:, 0] + offset[0]
        right = -points[:, 1] + offset[1]
        up = points[:, 2] + offset[2]
        safe = np.where(forward > 1e-6, forward, np.inf)
        col = w / 2 + focal * (w / self.width) * right / safe
        row = h / 2 - focal * (h / self.height) * up / safe
        return np.floor(row).astype(np.int64), np.floor(col).astype(np.int64), forward
