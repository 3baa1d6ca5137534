"""One synthetic drive: the world, the ego's trajectory and actions, moving cars, the anomaly.

The ego follows the right lane. Its speed comes from a controller on a target speed (cruise speed,
lower in curves, and for anomalous drives a stop before the object or a slow pass), and the speed
is integrated from the throttle and brake it outputs, so the actions explain the motion. Steering is
the kinematic bicycle angle for the lane's curvature (CARLA sign: positive steers right).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from umad_common.datasets.synthetic.anomalies import AnomalyShape, make_anomaly
from umad_common.datasets.synthetic.render import (
    WEATHERS,
    CameraFrame,
    CameraSpec,
    LidarSpec,
    Renderer,
    Weather,
    weather_named,
)
from umad_common.datasets.synthetic.world import (
    EGO_LANE_D,
    ONCOMING_LANE_D,
    STYLES,
    PrimSet,
    RoadCurve,
    build_static_world,
    car_parts,
)

FRAME_DT = 0.1  # 10 Hz, as AnoVox
WHEELBASE_M = 2.9
MAX_STEER_RAD = np.radians(35.0)
MAX_ACCEL, MAX_DECEL = 2.5, 6.0  # m/s^2 at full throttle / full brake
LATERAL_ACCEL = 2.0  # comfort limit in curves, m/s^2
SUN_AHEAD_DEG = (10.0, 40.0)  # with `sun_ahead`, the sun's azimuth lies this far either side of the road ahead
# With `sun_side`, the sun's azimuth lies this far from the road ahead, to the left or right: to the
# side and a little behind, so it lights the facades across the road and the building ends facing the
# camera, and never shines into the camera.
SUN_SIDE_DEG = (95.0, 125.0)
ROUTE_SIZE, ROUTE_PX_PER_M, ROUTE_EGO_FROM_BOTTOM, ROUTE_THICKNESS = 192, 5, 40, 16


@dataclass
class EgoTrack:
    """Per-frame ego state; s is the arc length of the centreline, speeds in m/s."""

    s: np.ndarray
    speed: np.ndarray
    throttle: np.ndarray
    brake: np.ndarray
    steer: np.ndarray
    curvature: np.ndarray  # of the driven lane, positive = left turn


@dataclass
class Anomaly:
    shape: AnomalyShape
    inst: int
    s: float
    d: float
    yaw: float  # world heading of the object (relative to the road until placed)
    behaviour: str  # "brake" (stop before it) or "pass" (drive by it slowly)
    position: tuple[float, float, float]


@dataclass
class MovingCar:
    """A car driving along a lane at constant speed (negative speed: against the road's direction)."""

    parts: list
    inst: int
    s_start: float
    speed: float
    d: float
    yaw_offset: float  # pi for oncoming cars


@dataclass
class SyntheticFrame:
    camera: CameraFrame
    lidar: np.ndarray  # (N, 4) float32 (x, y_left, z, intensity) = AnoVox's (x, -y, z, i)
    speed: float
    throttle: float
    brake: float
    steer: float
    pose: tuple[float, float, float]  # world x, y, heading (rad)
    route: np.ndarray  # (192, 192) uint8


def drive(
    road: RoadCurve, frames: int, cruise: float, v0: float, limit=None, stop: tuple[float, int] | None = None
) -> EgoTrack:
    """Simulate the ego with a speed controller.

    Args:
        limit: optional cap on the target speed as a function of s (slow pass of an object).
        stop: optional (s_stop, hold_frames): brake to a standstill at s_stop, wait, drive on.
    """
    s, v, held = 0.0, v0, 0
    out = {k: np.zeros(frames) for k in ("s", "speed", "throttle", "brake", "steer", "curvature")}
    for i in range(frames):
        kappa_c = float(road.curvature(np.array(s)))
        kappa = kappa_c / (1 - EGO_LANE_D * kappa_c)
        ahead = s + max(v, 2.0) * 1.0
        target = min(cruise, np.sqrt(LATERAL_ACCEL / max(np.abs(road.curvature(np.array([s, ahead]))).max(), 1e-6)))
        if limit is not None:
            target = min(target, limit(s), limit(s + v * 0.5))
        stopping = stop is not None and held < stop[1]
        if stopping:
            target = min(target, np.sqrt(max(0.0, 2 * 2.5 * (stop[0] - s - v * 0.3))))
        accel_cmd = np.clip(1.2 * (target - v), -MAX_DECEL, MAX_ACCEL)
        throttle = float(np.clip(accel_cmd / MAX_ACCEL, 0, 1))
        brake = float(np.clip(-accel_cmd / MAX_DECEL, 0, 1))
        if stopping and target < 0.3 and v < 0.3:
            throttle, brake = 0.0, 0.5  # holding the car at a standstill
            held += 1
        out["s"][i], out["speed"][i], out["throttle"][i], out["brake"][i] = s, v, throttle, brake
        out["curvature"][i] = kappa
        out["steer"][i] = float(np.clip(-np.arctan(WHEELBASE_M * kappa) / MAX_STEER_RAD, -1, 1))
        v_next = max(0.0, v + (MAX_ACCEL * throttle - MAX_DECEL * brake - 0.02 * v) * FRAME_DT)
        s += 0.5 * (v + v_next) * FRAME_DT / (1 - EGO_LANE_D * kappa_c)  # lane speed -> centreline arc length
        v = v_next
    return EgoTrack(**out)


class SyntheticScenario:
    """A deterministic drive: everything follows from (seed, frames, anomaly category, weather)."""

    def __init__(
        self,
        seed: int,
        frames: int,
        anomaly_category: str | None = None,
        weather: str | None = None,
        camera: CameraSpec | None = None,
        lidar: LidarSpec | None = None,
        wait_at: tuple[float, float] | None = None,
        direct_sunlight: bool = False,
        sun_ahead: bool = False,
        sun_side: bool = False,
        pole_spacing: tuple[float, float] | None = None,
        built_up: bool = False,
    ):
        """Args:
        weather: a preset's name (render.WEATHERS or render.EXTRA_WEATHERS); None: drawn from WEATHERS.
        wait_at: (nearest, farthest) gap in metres between the stopped ego and the anomaly: the
            ego brakes early in the drive to stand that far before the object and waits there
            to the end (the stress sets). None: the default benchmark's behaviours (a stop 5-9 m
            before the object, or a slow pass), drawn exactly as before.
        direct_sunlight: cast shadows, sun colour and lane-paint glare where the weather's sun
            shows (the light stress set); False: the default benchmark's evenly lit ground.
        sun_ahead: the sun stands SUN_AHEAD_DEG to the left or right of the road's heading where
            the drive ends (where the ego waits before the object), so a low sun faces the camera;
            False: any azimuth. Both draw nothing more from the seed's generator.
        sun_side: the sun stands SUN_SIDE_DEG to the left or right of that heading, so a low sun
            lights the facades beside the road rather than facing the camera (the facades stress
            set); draws nothing more. Not with `sun_ahead`.
        pole_spacing: (least, most) metres between the bare thin poles of a row along each
            sidewalk near the curb (world.build_static_world; the facades stress set); None: none.
        built_up: a drive whose drawn style is rural gets the suburban style instead (the same
            draw), so buildings line the road (the facades stress set); False: the drawn style.
        """
        if frames < 1:
            raise ValueError(f"frames must be >= 1, got {frames}")
        if sun_ahead and sun_side:
            raise ValueError("sun_ahead and sun_side exclude each other")
        if pole_spacing is not None and not 0 < pole_spacing[0] <= pole_spacing[1]:
            raise ValueError(f"pole_spacing must be (least, most) metres with 0 < least <= most, got {pole_spacing}")
        if wait_at is not None and not 0 < wait_at[0] <= wait_at[1]:
            raise ValueError(f"wait_at must be (nearest, farthest) metres with 0 < nearest <= farthest, got {wait_at}")
        rng = np.random.default_rng(seed)
        self.seed, self.frames = seed, frames
        self.camera, self.lidar = camera or CameraSpec(), lidar or LidarSpec()
        if weather is None:
            self.weather: Weather = WEATHERS[rng.integers(len(WEATHERS))]
        else:
            self.weather = weather_named(weather)
        style_index = int(rng.integers(len(STYLES)))
        self.style = STYLES[min(style_index, 1) if built_up else style_index]  # STYLES: urban, suburban, rural
        cruise = rng.uniform(8.0, 11.0)
        reach = frames * FRAME_DT * cruise * 1.2 + 250
        self.road = RoadCurve(rng, reach)
        v0 = cruise * rng.uniform(0.6, 1.0)
        free = drive(self.road, frames, cruise, v0)

        self.anomaly: Anomaly | None = None
        limit, stop = None, None
        if anomaly_category is not None:
            shape = make_anomaly(rng, anomaly_category)
            behaviour = "brake" if rng.random() < 0.5 or wait_at is not None else "pass"
            half_extent = max(shape.size[0], shape.size[1]) / 2
            if behaviour == "brake" and wait_at is not None:  # stop far away early, wait to the end
                s_stop = rng.uniform(15.0, 25.0)  # brakes at once: standing still after about 5 s
                s_a = s_stop + rng.uniform(*wait_at) + half_extent
                d_a = EGO_LANE_D + rng.uniform(-0.6, 0.6)
                stop = (s_stop, frames)
            elif behaviour == "brake":
                s_stop = float(free.s[int(frames * rng.uniform(0.25, 0.45))])
                s_a = s_stop + rng.uniform(5.0, 9.0) + half_extent
                d_a = EGO_LANE_D + rng.uniform(-0.6, 0.6)
                stop = (s_stop, frames)
            else:
                s_a = float(free.s[int(frames * rng.uniform(0.6, 0.75))])
                d_a = max(ONCOMING_LANE_D + rng.uniform(-0.3, 0.5), -0.85 + 0.5 + half_extent)
                limit = lambda s: np.sqrt(4.5**2 + 2 * 2.0 * max(0.0, s_a - 30 - s)) if s < s_a + 5 else np.inf  # noqa: E731
            yaw = rng.uniform(-np.pi, np.pi)
            self.anomaly = Anomaly(shape, 0, float(s_a), float(d_a), yaw, behaviour, (0.0, 0.0, 0.0))
        elif rng.random() < 0.35:  # normal drives stop now and then too (a stop line, a crossing)
            stop = (float(free.s[int(frames * rng.uniform(0.2, 0.7))]), int(rng.integers(10, 50)))
        self.track = drive(self.road, frames, cruise, v0, limit, stop) if (limit or stop) else free

        s_end = float(self.track.s[-1])
        keep_clear = [(self.anomaly.s, self.anomaly.d)] if self.anomaly else []
        self.static, next_inst = build_static_world(
            rng, self.road, (-60.0, s_end + 170.0), self.style, keep_clear, pole_spacing
        )
        self.movers = self._plan_movers(rng, next_inst, cruise, s_end)
        next_inst += len(self.movers)
        self.anomaly_prims = PrimSet()
        if self.anomaly is not None:
            a = self.anomaly
            x, y, heading = (float(v) for v in self.road.to_world(np.array(a.s), np.array(a.d)))
            a.inst, a.yaw, a.position = next_inst, heading + a.yaw, (x, y, 0.0)
            self.anomaly_prims = PrimSet.from_parts(a.shape.parts, x, y, a.yaw, a.inst)
        sun_azimuth = rng.uniform(-np.pi, np.pi)
        if sun_ahead:  # the same draw, mapped to SUN_AHEAD_DEG either side of the road's end heading
            side = np.sign(sun_azimuth) or 1.0
            offset = np.radians(SUN_AHEAD_DEG[0] + (SUN_AHEAD_DEG[1] - SUN_AHEAD_DEG[0]) * abs(sun_azimuth) / np.pi)
            sun_azimuth = self.pose(frames - 1)[2] + side * offset
        elif sun_side:  # the same draw, mapped to SUN_SIDE_DEG either side of the road's end heading
            side = np.sign(sun_azimuth) or 1.0
            offset = np.radians(SUN_SIDE_DEG[0] + (SUN_SIDE_DEG[1] - SUN_SIDE_DEG[0]) * abs(sun_azimuth) / np.pi)
            sun_azimuth = self.pose(frames - 1)[2] + side * offset
        self.renderer = Renderer(
            self.road, self.weather, self.camera, self.lidar, seed, sun_azimuth, direct_sunlight=direct_sunlight
        )

    def _plan_movers(self, rng: np.random.Generator, first_inst: int, cruise: float, s_end: float) -> list[MovingCar]:
        """Oncoming cars, and in normal drives sometimes a faster lead car in the ego lane."""
        movers = []
        s_lo, s_hi = 25.0, s_end + 160.0
        if self.anomaly is not None and self.anomaly.d > 0:
            s_hi = min(s_hi, self.anomaly.s - 8.0)  # oncoming cars must not drive through the object
        for k in range(int(rng.integers(2, 7))):
            if s_hi <= s_lo:
                break
            movers.append(
                MovingCar(
                    car_parts(rng), first_inst + k, rng.uniform(s_lo, s_hi), -rng.uniform(6, 11), ONCOMING_LANE_D, np.pi
                )
            )
        if self.anomaly is None and rng.random() < 0.5:
            movers.append(
                MovingCar(car_parts(rng), first_inst + len(movers), rng.uniform(20, 35), cruise + 1.5, EGO_LANE_D, 0.0)
            )
        return movers

    def pose(self, i: int) -> tuple[float, float, float]:
        """Ego (camera) pose at frame i: world x, y and heading."""
        x, y, heading = self.road.to_world(np.array(self.track.s[i]), np.array(EGO_LANE_D))
        return float(x), float(y), float(heading)

    def prims_at(self, i: int) -> PrimSet:
        """Static world, moving cars at frame i, and the anomaly."""
        sets = [self.static, self.anomaly_prims]
        for car in self.movers:
            s = car.s_start + car.speed * i * FRAME_DT
            x, y, heading = self.road.to_world(np.array(s), np.array(car.d))
            sets.append(PrimSet.from_parts(car.parts, float(x), float(y), float(heading) + car.yaw_offset, car.inst))
        return PrimSet.concat(sets)

    def route_map(self, i: int) -> np.ndarray:
        """192x192 route raster: lane centreline 16 px thick, 5 px/m, ego 40 px from the bottom, heading up."""
        x0, y0, heading = self.pose(i)
        s = self.track.s[i] + np.arange(-10.0, 40.0, 1.0)
        x, y, _ = self.road.to_world(s, np.full_like(s, EGO_LANE_D))
        c, sn = np.cos(heading), np.sin(heading)
        fwd = (x - x0) * c + (y - y0) * sn
        left = -(x - x0) * sn + (y - y0) * c
        cols = ROUTE_SIZE / 2 - left * ROUTE_PX_PER_M
        rows = ROUTE_SIZE - ROUTE_EGO_FROM_BOTTOM - fwd * ROUTE_PX_PER_M
        route = np.zeros((ROUTE_SIZE, ROUTE_SIZE), np.uint8)
        pts = np.round(np.stack([cols, rows], axis=1)).astype(np.int32)
        cv2.polylines(route, [pts], False, 255, ROUTE_THICKNESS)
        return route

    def render(self, i: int, with_lidar: bool = True) -> SyntheticFrame:
        """All sensors and the ego state of frame i."""
        pose = self.pose(i)
        prims = self.prims_at(i)
        camera = self.renderer.render_camera(pose, prims, i)
        lidar = self.renderer.render_lidar(pose, prims) if with_lidar else np.zeros((0, 4), np.float32)
        t = self.track
        return SyntheticFrame(
            camera,
            lidar,
            float(t.speed[i]),
            float(t.throttle[i]),
            float(t.brake[i]),
            float(t.steer[i]),
            pose,
            self.route_map(i),
        )
