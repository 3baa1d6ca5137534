"""Sensors of the synthetic world: the FOV-90 camera (rgb, CARLA depth, semantic tags, instances) and
the 64-channel lidar, both cast against the same geometry; weather and time-of-day presets.

The default benchmark lights the ground evenly. With `direct_sunlight`, a sun that stands up and is
not hidden by clouds casts soft shadows of every primitive on the ground (shadows.py), tints what it
lights with its colour, and makes lane paint glare where it mirrors the sun (a low sun ahead)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import cv2
import numpy as np

from umad_common.datasets.synthetic.raycast import (
    GROUND_ROAD,
    GROUND_SIDEWALK,
    GroundHit,
    camera_rects,
    intersect_ground,
    intersect_prims,
    spherical_rects,
    unit_normal,
)
from umad_common.datasets.synthetic.shadows import MIN_SUN_HEIGHT, GroundShadowMap
from umad_common.datasets.synthetic.world import (
    LANE_WIDTH,
    MAT_FOLIAGE,
    MAT_GLASS,
    MAT_LAMP,
    MAT_ROUGH,
    MAT_SPOTS,
    MAT_STRIPES,
    MAT_WINDOWS,
    TAG_ROAD,
    TAG_ROAD_LINE,
    TAG_SIDEWALK,
    TAG_SKY,
    TAG_TERRAIN,
    PrimSet,
    RoadCurve,
)

SKY_DEPTH_M = 1000.0  # CARLA's far plane: sky pixels decode to 1000 m
CULL_RANGE_M = 150.0
LANE_GLARE_GAIN = 3.0  # peak glare of lane paint that mirrors the sun, times the sun's strength
LANE_GLARE_EXPONENT = 40  # how narrow the glare's lobe around the mirror direction is


@dataclass(frozen=True)
class Weather:
    """A weather and time-of-day preset."""

    name: str
    sky_top: tuple[float, float, float]
    sky_horizon: tuple[float, float, float]
    sun_elevation_deg: float
    sun_colour: tuple[float, float, float]
    sun_strength: float
    ambient: float
    fog_density: float  # per metre
    fog_colour: tuple[float, float, float]
    cloud: float = 0.0
    rain: bool = False
    night: bool = False

    @property
    def sun_casts_shadows(self) -> bool:
        """Whether the sun stands up and the sky is clear enough for it to cast shadows."""
        return (
            self.sun_strength > 0 and np.sin(np.radians(self.sun_elevation_deg)) >= MIN_SUN_HEIGHT and self.cloud < 0.5
        )


WEATHERS = (
    Weather(
        "clear_noon",
        (0.25, 0.45, 0.80),
        (0.70, 0.80, 0.92),
        60,
        (1.0, 0.97, 0.9),
        0.7,
        0.55,
        0.003,
        (0.75, 0.82, 0.90),
        0.2,
    ),
    Weather(
        "cloudy",
        (0.52, 0.55, 0.60),
        (0.76, 0.77, 0.79),
        45,
        (1.0, 1.0, 1.0),
        0.18,
        0.78,
        0.006,
        (0.72, 0.73, 0.75),
        0.85,
    ),
    Weather(
        "rain",
        (0.33, 0.35, 0.38),
        (0.55, 0.56, 0.58),
        40,
        (1.0, 1.0, 1.0),
        0.06,
        0.62,
        0.014,
        (0.50, 0.52, 0.55),
        0.9,
        rain=True,
    ),
    Weather(
        "fog", (0.70, 0.71, 0.73), (0.78, 0.79, 0.80), 40, (1.0, 1.0, 1.0), 0.12, 0.72, 0.045, (0.76, 0.77, 0.78), 0.3
    ),
    Weather(
        "dusk",
        (0.20, 0.24, 0.45),
        (0.95, 0.56, 0.32),
        7,
        (1.0, 0.62, 0.36),
        0.75,
        0.38,
        0.005,
        (0.80, 0.56, 0.42),
        0.35,
    ),
    Weather(
        "night",
        (0.01, 0.015, 0.04),
        (0.05, 0.06, 0.10),
        -20,
        (0.0, 0.0, 0.0),
        0.0,
        0.07,
        0.008,
        (0.04, 0.045, 0.06),
        0.0,
        night=True,
    ),
)
WEATHER_NAMES = tuple(w.name for w in WEATHERS)  # the presets the default benchmark cycles through
# Presets only the stress sets use (adding one to WEATHERS would change the default benchmark's drives).
EXTRA_WEATHERS = (
    Weather(
        "sunset",
        (0.28, 0.36, 0.62),
        (1.0, 0.70, 0.45),
        15,
        (1.0, 0.78, 0.55),
        1.3,
        0.32,
        0.003,
        (0.85, 0.70, 0.58),
        0.15,
    ),
)


def weather_named(name: str) -> Weather:
    """The preset called `name`, from WEATHERS or EXTRA_WEATHERS."""
    for weather in (*WEATHERS, *EXTRA_WEATHERS):
        if weather.name == name:
            return weather
    raise ValueError(f"unknown weather {name!r}; expected one of {[w.name for w in (*WEATHERS, *EXTRA_WEATHERS)]}")


@dataclass(frozen=True)
class CameraSpec:
    """Pinhole camera looking along the ego's x axis, principal point at the image centre."""

    width: int = 384
    height: int = 256
    fov_deg: float = 90.0
    mount_height: float = 1.8

    @property
    def focal(self) -> float:
        return self.width / 2 / np.tan(np.radians(self.fov_deg) / 2)

    def rays(self) -> np.ndarray:
        """(H*W, 3) ego-frame directions (x forward = 1, y left, z up) through the pixel centres."""
        u = (np.arange(self.width) + 0.5 - self.width / 2) / self.focal
        v = (np.arange(self.height) + 0.5 - self.height / 2) / self.focal
        vv, uu = np.meshgrid(v, u, indexing="ij")
        return np.stack([np.ones_like(uu), -uu, -vv], axis=-1).reshape(-1, 3)


@dataclass(frozen=True)
class LidarSpec:
    """Spinning lidar: 64 channels from +15 to -25 degrees, azimuth bins over 360, 100 m range."""

    channels: int = 64
    upper_deg: float = 15.0
    lower_deg: float = -25.0
    azimuth_bins: int = 512
    max_range: float = 100.0
    mount_height: float = 1.8

    def elevations(self) -> np.ndarray:
        return np.radians(np.linspace(self.upper_deg, self.lower_deg, self.channels))

    def rays(self) -> np.ndarray:
        """(channels*bins, 3) unit directions in the sensor frame, channel-major."""
        el = self.elevations()[:, None]
        az = ((np.arange(self.azimuth_bins) + 0.5) * 2 * np.pi / self.azimuth_bins - np.pi)[None, :]
        dirs = np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), axis=-1)
        return dirs.reshape(-1, 3)


@cache
def noise_texture(size: int = 256) -> np.ndarray:
    """A fixed, tileable smooth noise in [-1, 1] (low-pass filtered white noise)."""
    white = np.random.default_rng(20240611).standard_normal((size, size))
    f = np.fft.fftfreq(size)
    radius = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    smooth = np.real(np.fft.ifft2(np.fft.fft2(white) / (1 + (radius * 40) ** 2)))
    return (smooth / np.abs(smooth).max()).astype(np.float32)


def noise(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup of the noise texture at texel coordinates (u, v), wrapping."""
    tex = noise_texture()
    n, count = tex.shape[0], np.size(u)
    rows = -(-count // 512)
    maps = np.zeros((2, rows * 512), np.float32)  # cv2.remap wants 2-D maps under 32767 rows
    maps[0, :count] = np.mod(np.ravel(u), n)
    maps[1, :count] = np.mod(np.ravel(v), n)
    out = cv2.remap(
        tex, maps[0].reshape(rows, 512), maps[1].reshape(rows, 512), cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP
    )
    return out.ravel()[:count].reshape(np.shape(u)).astype(np.float64)


def rotation_to_world(heading: float) -> np.ndarray:
    c, s = np.cos(heading), np.sin(heading)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class CameraFrame:
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32, planar depth in metres, sky = 1000
    semantic: np.ndarray  # (H, W) uint8 CARLA tags
    instance: np.ndarray  # (H, W) int32 object ids, 0 = none


class Renderer:
    """Renders one scenario's sensors for ego poses (x, y, heading) and the primitives of the moment."""

    def __init__(
        self,
        road: RoadCurve,
        weather: Weather,
        camera: CameraSpec,
        lidar: LidarSpec,
        seed: int,
        sun_azimuth: float,
        direct_sunlight: bool = False,
    ):
        """Args:
        direct_sunlight: light the ground as a visible sun does (cast shadows, its colour, glare on
            lane paint) when the weather's sun casts shadows; False: the default benchmark's evenly
            lit ground.
        """
        self.road, self.weather, self.camera, self.lidar, self.seed = road, weather, camera, lidar, seed
        self.direct_sunlight = direct_sunlight and weather.sun_casts_shadows
        self.camera_rays = camera.rays()
        self.camera_ray_len = np.linalg.norm(self.camera_rays, axis=1)
        self.lidar_rays = lidar.rays()
        el = np.radians(weather.sun_elevation_deg)
        self.sun = np.array([np.cos(el) * np.cos(sun_azimuth), np.cos(el) * np.sin(sun_azimuth), np.sin(el)])

    def render_camera(self, pose: tuple[float, float, float], prims: PrimSet, frame_index: int) -> CameraFrame:
        cam = self.camera
        rot = rotation_to_world(pose[2])
        origin = np.array([pose[0], pose[1], cam.mount_height])
        dirs = np.einsum("ij,nj->ni", rot, self.camera_rays)
        near = np.hypot(prims.center[:, 0] - pose[0], prims.center[:, 1] - pose[1]) < CULL_RANGE_M
        corners_ego = (prims.corners() - origin) @ rot  # (P, 8, 3) in ego axes
        corners_cam = np.stack([-corners_ego[..., 1], -corners_ego[..., 2], corners_ego[..., 0]], axis=-1)
        rects = camera_rects(corners_cam, cam.focal, cam.width, cam.height)
        rects[~near] = 0
        ground = intersect_ground(origin, dirs, self.road)
        hit = intersect_prims(origin, dirs, (cam.height, cam.width), prims, rects)
        use_prim = hit.t < ground.t
        t = np.where(use_prim, hit.t, ground.t)
        sky = ~np.isfinite(t)

        semantic = np.full(len(dirs), TAG_SKY, np.uint8)
        instance = np.zeros(len(dirs), np.int32)
        ground_px = ~use_prim & ~sky
        surface = ground.surface[ground_px]
        line = self._lane_line(ground.s[ground_px], ground.d[ground_px]) & (surface == GROUND_ROAD)
        lut = np.array([TAG_ROAD, TAG_SIDEWALK, TAG_TERRAIN], np.uint8)
        semantic[ground_px] = np.where(line, TAG_ROAD_LINE, lut[surface])
        semantic[use_prim] = prims.tag[hit.prim[use_prim]]
        instance[use_prim] = prims.inst[hit.prim[use_prim]]

        colour = np.zeros((len(dirs), 3))
        colour[sky] = self._sky(dirs[sky])
        rng_m = t * self.camera_ray_len
        albedo = self._ground_albedo(ground, line, ground_px, origin, dirs, rng_m)
        if self.direct_sunlight:
            points = origin + t[ground_px, None] * dirs[ground_px]
            shadow = GroundShadowMap(prims, self.sun, pose[:2], pose[2]).at(points)
            colour[ground_px] = self._sunlit_ground(albedo, shadow, line, dirs[ground_px])
        else:
            colour[ground_px] = albedo * (self.weather.ambient + self.weather.sun_strength * max(self.sun[2], 0.0))
        if use_prim.any():
            colour[use_prim] = self._shade_prims(
                prims, hit.prim[use_prim], origin, dirs[use_prim], t[use_prim], rng_m[use_prim]
            )
        if self.weather.night:
            boost = 1 + self._headlights(rng_m[~sky], self.camera_rays[~sky]) / self.weather.ambient
            colour[~sky] *= boost[:, None]
            colour[use_prim] = np.where(
                (prims.material[hit.prim[use_prim]] == MAT_LAMP)[:, None], (1.0, 0.92, 0.7), colour[use_prim]
            )
        solid = ~sky
        fog = (1 - np.exp(-self.weather.fog_density * rng_m[solid]))[:, None]
        colour[solid] = colour[solid] * (1 - fog) + np.array(self.weather.fog_colour) * fog
        image = colour.reshape(cam.height, cam.width, 3)
        if self.weather.rain:
            image = self._rain(image, frame_index)
        rgb = np.clip(image * 255 + 0.5, 0, 255).astype(np.uint8)
        depth = np.where(sky, SKY_DEPTH_M, np.minimum(t, SKY_DEPTH_M)).astype(np.float32)
        shape = (cam.height, cam.width)
        return CameraFrame(rgb, depth.reshape(shape), semantic.reshape(shape), instance.reshape(shape))

    def render_lidar(self, pose: tuple[float, float, float], prims: PrimSet) -> np.ndarray:
        """(N, 4) float32 points (x forward, y left, z up relative to the sensor, intensity)."""
        spec = self.lidar
        rot = rotation_to_world(pose[2])
        origin = np.array([pose[0], pose[1], spec.mount_height])
        dirs = np.einsum("ij,nj->ni", rot, self.lidar_rays)
        corners = (prims.corners() - origin) @ rot
        rects = spherical_rects(corners, spec.elevations(), spec.azimuth_bins, spec.max_range)
        ground = intersect_ground(origin, dirs, self.road)
        hit = intersect_prims(origin, dirs, (spec.channels, spec.azimuth_bins), prims, rects)
        t = np.minimum(ground.t, hit.t)
        keep = t <= spec.max_range
        points = self.lidar_rays[keep] * t[keep, None]
        intensity = np.exp(-0.004 * t[keep])
        return np.concatenate([points, intensity[:, None]], axis=1).astype(np.float32)

    @staticmethod
    def _lane_line(s: np.ndarray, d: np.ndarray) -> np.ndarray:
        centre = (np.abs(d) < 0.08) & (np.mod(s, 9.0) < 3.0)
        edge = np.abs(np.abs(d) - LANE_WIDTH) < 0.07
        return centre | edge

    def _sky(self, dirs: np.ndarray) -> np.ndarray:
        w = self.weather
        unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        up = np.clip(unit[:, 2], 0, 1)
        mix = (up**0.6)[:, None]
        colour = np.array(w.sky_horizon) * (1 - mix) + np.array(w.sky_top) * mix
        if w.cloud > 0:
            lift = np.maximum(unit[:, 2], 0.03) + 0.05
            cloud = noise(unit[:, 0] / lift * 9 + 31.0, unit[:, 1] / lift * 9 + 17.0)
            amount = np.clip((cloud + 0.25 - 0.5 * (1 - w.cloud)) * 1.6, 0, 1) * np.clip(up * 6, 0, 1)
            cloud_colour = np.array(w.sky_horizon) * 1.05 if not w.night else np.array(w.sky_top)
            colour = colour * (1 - amount[:, None] * w.cloud) + cloud_colour * amount[:, None] * w.cloud
        if w.sun_strength > 0:
            glow = np.clip(np.einsum("nj,j->n", unit, self.sun), 0, 1)
            colour = (
                colour + np.array(w.sun_colour) * (0.35 * glow**24 + 0.8 * (glow > 0.9995))[:, None] * w.sun_strength
            )
        return colour

    def _ground_albedo(
        self,
        ground: GroundHit,
        line: np.ndarray,
        px: np.ndarray,
        origin: np.ndarray,
        dirs: np.ndarray,
        rng_m: np.ndarray,
    ) -> np.ndarray:
        """Albedo of the ground pixels `px`: textured asphalt with paint, sidewalk tiles, grass and dirt."""
        w = self.weather
        s, d, surface, t = ground.s[px], ground.d[px], ground.surface[px], ground.t[px]
        x = origin[0] + t * dirs[px, 0]
        y = origin[1] + t * dirs[px, 1]
        rng_m = rng_m[px]
        fade = np.clip(30.0 / np.maximum(rng_m, 1.0), 0, 1)
        coarse = noise(x * 0.35, y * 0.35)
        fine = noise(x * 3.0 + 91, y * 3.0 + 57) * fade
        asphalt = 0.30 * (1 + 0.12 * coarse + 0.10 * fine)
        road = np.stack([asphalt, asphalt, asphalt * 1.03], axis=1)
        if w.rain:
            road = road * 0.65 + np.array(w.sky_horizon) * 0.12
        paint = np.array([0.80, 0.80, 0.76]) * (0.9 + 0.1 * fine)[:, None]
        road = np.where(line[:, None], paint, road)
        seam = ((np.mod(s, 1.5) < 0.05) | (np.mod(d, 1.5) < 0.05)) & (rng_m < 25)
        walk = np.array([0.58, 0.56, 0.53]) * (1 + 0.06 * coarse - 0.12 * seam)[:, None]
        dirt = np.clip(noise(x * 0.08 + 13, y * 0.08 + 71) * 1.5 + 0.2, 0, 1)[:, None]
        grass = np.array([0.27, 0.38, 0.15]) * (1 - dirt * 0.6) + np.array([0.42, 0.35, 0.24]) * dirt * 0.6
        grass = grass * (1 + 0.2 * coarse + 0.25 * fine)[:, None]
        base = np.where(
            (surface == GROUND_ROAD)[:, None], road, np.where((surface == GROUND_SIDEWALK)[:, None], walk, grass)
        )
        return base

    def _sunlit_ground(self, albedo: np.ndarray, shadow: np.ndarray, line: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Ground colours relit by the direct sun: ambient light everywhere, the sun's coloured light
        where no shadow falls, and glare on lane paint seen near the sun's mirror direction.

        Args:
            albedo: (N, 3) from `_ground_albedo`.
            shadow: (N,) in [0, 1], 1 where the sun is hidden.
            line: (N,) lane paint.
            dirs: (N, 3) the camera rays that met these points.
        """
        w = self.weather
        direct = w.sun_strength * self.sun[2]
        sun_colour = np.array(w.sun_colour)
        light = w.ambient + (direct * (1 - shadow))[:, None] * sun_colour
        mirrored = dirs * np.array([1.0, 1.0, -1.0]) / np.linalg.norm(dirs, axis=1, keepdims=True)
        lobe = np.clip(mirrored @ self.sun, 0.0, 1.0) ** LANE_GLARE_EXPONENT
        glare = LANE_GLARE_GAIN * w.sun_strength * lobe * line * (1 - shadow)
        return albedo * light + glare[:, None] * sun_colour

    def _shade_prims(
        self, prims: PrimSet, idx: np.ndarray, origin: np.ndarray, dirs: np.ndarray, t: np.ndarray, rng_m: np.ndarray
    ) -> np.ndarray:
        """Colours of primitive hits: base colour and material pattern, sun and sky light."""
        w = self.weather
        m = prims.world_to_unit()[idx]
        p_world = origin + t[:, None] * dirs
        p_unit = np.einsum("nij,nj->ni", m, p_world - prims.center[idx])
        n_unit = unit_normal(prims.kind[idx], p_unit)
        normal = np.einsum("nji,nj->ni", m, n_unit)
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
        base = prims.colour[idx].copy()
        material = prims.material[idx]
        metres = p_unit * prims.half[idx]
        fade = np.clip(25.0 / np.maximum(rng_m, 1.0), 0, 1)

        facade = (material == MAT_WINDOWS) & (np.abs(normal[:, 2]) < 0.5)
        along = np.where(np.abs(n_unit[:, 0]) > 0.5, metres[:, 1], metres[:, 0])
        height = p_world[:, 2]
        window = (
            facade
            & (np.mod(along, 3.0) > 0.8)
            & (np.mod(along, 3.0) < 2.2)
            & (np.mod(height, 3.2) > 1.1)
            & (np.mod(height, 3.2) < 2.5)
            & (height > 1.0)
        )
        glass = np.array([0.13, 0.16, 0.21]) + 0.15 * np.array(w.sky_horizon)
        if w.night:
            cell = np.floor(along / 3.0) * 7.0 + np.floor(height / 3.2) * 13.0 + prims.inst[idx] * 3.0
            lit = noise(cell * 1.7, cell * 0.3) > 0.15
            glass = np.where(lit[:, None], (1.6, 1.3, 0.7), glass)
        base = np.where(window[:, None], glass, base)
        roof = (material == MAT_WINDOWS) & (normal[:, 2] > 0.5)
        base[roof] *= 0.6
        cabin_side = (material == MAT_GLASS) & (np.abs(n_unit[:, 2]) < 0.5)
        base[cabin_side] = (0.10, 0.12, 0.15) + 0.2 * np.array(w.sky_horizon)
        angle = np.arctan2(p_unit[:, 1], p_unit[:, 0])
        foliage = material == MAT_FOLIAGE
        base[foliage] *= (
            0.7 + 0.45 * noise(angle * 6 + idx * 3.1, metres[:, 2] * 2.5)[foliage] * (0.4 + 0.6 * fade[foliage])
        )[:, None]
        rough = material == MAT_ROUGH
        base[rough] *= (0.8 + 0.3 * noise(angle * 4 + metres[:, 2] * 5, metres[:, 2] * 3 + idx)[rough])[:, None]
        spots = (material == MAT_SPOTS) & (noise(angle * 3 + 40, metres[:, 2] * 6 + 40) > 0.2)
        base[spots] = (0.12, 0.09, 0.07)
        stripes = (material == MAT_STRIPES) & (np.mod(p_world[:, 2], 0.4) < 0.15)
        base[stripes] = (0.95, 0.95, 0.95)

        sun = np.clip(np.einsum("nj,j->n", normal, self.sun), 0, None) * w.sun_strength
        sky_light = w.ambient * (0.7 + 0.3 * normal[:, 2])
        if self.direct_sunlight:
            lit = base * (sky_light[:, None] + sun[:, None] * np.array(w.sun_colour))
        else:
            lit = base * (sky_light + sun)[:, None]
        emissive = window & w.night
        return np.where(emissive[:, None], base, lit)

    @staticmethod
    def _headlights(rng_m: np.ndarray, rays_ego: np.ndarray) -> np.ndarray:
        lateral = rays_ego[:, 1] / rays_ego[:, 0]
        vertical = rays_ego[:, 2] / rays_ego[:, 0]
        forward = rays_ego[:, 0] > 0
        cone = np.exp(-((lateral / 0.5) ** 2) - ((vertical + 0.12) / 0.22) ** 2) * forward
        return 1.2 * cone * np.exp(-rng_m / 35.0)

    def _rain(self, image: np.ndarray, frame_index: int) -> np.ndarray:
        h, w = image.shape[:2]
        rng = np.random.default_rng([self.seed, frame_index, 7])
        count = int(0.003 * h * w)
        start = rng.uniform(0, 1, (count, 2)) * (w, h)
        length = rng.uniform(0.03, 0.07, count) * h
        end = start + np.stack([length * 0.15, length], axis=1)
        mask = np.zeros((h, w), np.uint8)
        lines = np.stack([start, end], axis=1).round().astype(np.int32)
        cv2.polylines(mask, list(lines), False, 255, 1)
        alpha = (mask.astype(np.float64) / 255 * 0.22)[..., None]
        return image * 0.92 * (1 - alpha) + 0.8 * alpha
