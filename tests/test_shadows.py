"""The sun's cast shadows and lane glare in the synthetic renderer, and the default benchmark they leave alone."""

from __future__ import annotations

import hashlib
from dataclasses import replace

import numpy as np
import pytest

from umad_common.datasets.synthetic.generator import plan_benchmark
from umad_common.datasets.synthetic.render import (
    WEATHERS,
    CameraSpec,
    LidarSpec,
    Renderer,
    weather_named,
)
from umad_common.datasets.synthetic.scenario import SyntheticScenario
from umad_common.datasets.synthetic.shadows import GroundShadowMap
from umad_common.datasets.synthetic.world import KIND_BOX, TAG_BUILDING, Part, PrimSet, RoadCurve

SMALL = CameraSpec(width=96, height=64)
CAMERA = CameraSpec(width=192, height=128)


def sun_towards(azimuth: float, elevation_deg: float) -> np.ndarray:
    el = np.radians(elevation_deg)
    return np.array([np.cos(el) * np.cos(azimuth), np.cos(el) * np.sin(azimuth), np.sin(el)])


def block(x: float, y: float, height: float = 4.0) -> PrimSet:
    """A 2 m x 2 m block of `height` standing on the ground at world (x, y)."""
    return PrimSet.from_parts(
        [Part(KIND_BOX, (0, 0, height / 2), (1.0, 1.0, height / 2), TAG_BUILDING, (0.5, 0.5, 0.5))], x, y, 0.0, 5
    )


def test_shadow_map_darkens_the_ground_behind_a_block_and_nowhere_else():
    sun = sun_towards(0.0, 30.0)  # ahead (+x), 30 degrees up: a 4 m block throws 6.9 m of shadow toward -x
    shadow = GroundShadowMap(block(20.0, 0.0), sun, (0.0, 0.0), 0.0)
    points = np.array(
        [
            [16.0, 0.0, 0.0],  # behind the block, mid-shadow
            [12.5, 0.0, 0.0],  # near the shadow's tip (21 - 6.93 = 14.07 from the far top edge)
            [15.0, 0.0, 0.15],  # on a raised sidewalk, still in the shadow
            [25.0, 0.0, 0.0],  # the sunny side
            [16.0, 4.0, 0.0],  # beside the shadow
            [11.0, 0.0, 0.0],  # beyond its tip
        ]
    )
    got = shadow.at(points)
    assert np.all(got[:3] > 0.9) and np.all(got[3:] < 0.05), got


def test_shadow_map_follows_the_sun_and_the_camera_heading():
    sun = sun_towards(np.pi / 2, 45.0)  # the sun in +y: the shadow falls toward -y
    heading = 0.7  # the map turns with the camera; the answer must not
    shadow = GroundShadowMap(block(30.0, 0.0), sun, (5.0, -2.0), heading)
    got = shadow.at(np.array([[30.0, -2.5, 0.0], [30.0, 2.5, 0.0]]))
    assert got[0] > 0.9 and got[1] < 0.05, got
    with pytest.raises(ValueError, match="at least"):
        GroundShadowMap(block(30.0, 0.0), sun_towards(0.0, 1.0), (0.0, 0.0), 0.0)


def pixel_of(point: np.ndarray, pose: tuple[float, float, float], camera: CameraSpec) -> tuple[int, int]:
    """(row, column) of a world point in the camera at `pose`."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    dx, dy, dz = point[0] - pose[0], point[1] - pose[1], point[2] - camera.mount_height
    ahead, left = c * dx + s * dy, -s * dx + c * dy
    return int(camera.height / 2 - camera.focal * dz / ahead), int(camera.width / 2 - camera.focal * left / ahead)


def test_renderer_shades_the_cast_shadow_and_leaves_open_ground_as_it_was():
    road = RoadCurve(np.random.default_rng(3), 300.0)
    x0, y0, heading = (float(v) for v in road.to_world(np.array(0.0), np.array(-1.75)))
    pose = (x0, y0, heading)
    bx, by, _ = (float(v) for v in road.to_world(np.array(25.0), np.array(-1.0)))
    prims = block(bx, by)
    white_noon = replace(WEATHERS[0], sun_colour=(1.0, 1.0, 1.0))  # so open ground keeps its colour exactly
    sun_azimuth = heading  # the sun ahead: the shadow falls toward the camera along the road
    even, sunlit = (
        Renderer(road, white_noon, CAMERA, LidarSpec(), 0, sun_azimuth, direct_sunlight=flag).render_camera(
            pose, prims, 0
        )
        for flag in (False, True)
    )
    in_shadow = pixel_of(np.array([*road.to_world(np.array(22.0), np.array(-1.0))[:2], 0.0]), pose, CAMERA)
    in_open = pixel_of(np.array([*road.to_world(np.array(12.0), np.array(1.5))[:2], 0.0]), pose, CAMERA)
    assert even.semantic[in_shadow] == sunlit.semantic[in_shadow] == 1  # road, in both
    shadowed, lit = sunlit.rgb[in_shadow].astype(int), even.rgb[in_shadow].astype(int)
    assert shadowed.sum() < 0.7 * lit.sum(), f"shadowed road {shadowed}, evenly lit {lit}"
    assert np.abs(sunlit.rgb[in_open].astype(int) - even.rgb[in_open].astype(int)).max() <= 1
    np.testing.assert_array_equal(sunlit.semantic, even.semantic)
    np.testing.assert_array_equal(sunlit.depth, even.depth)


def test_lane_paint_glares_toward_a_low_sun_ahead():
    road = RoadCurve(np.random.default_rng(3), 300.0)
    pose = tuple(float(v) for v in road.to_world(np.array(0.0), np.array(-1.75)))
    sunset = weather_named("sunset")
    frames = {
        azimuth: Renderer(road, sunset, CAMERA, LidarSpec(), 0, azimuth, direct_sunlight=True).render_camera(
            pose, PrimSet(), 0
        )
        for azimuth in (pose[2], pose[2] + np.pi)  # ahead, behind
    }
    ahead, behind = frames[pose[2]], frames[pose[2] + np.pi]
    paint = ahead.semantic == 24
    assert paint.sum() > 20
    assert ahead.rgb[paint].astype(float).mean() > behind.rgb[paint].astype(float).mean() + 40


def test_only_a_visible_sun_casts_shadows():
    casts = {w.name: w.sun_casts_shadows for w in (*WEATHERS, weather_named("sunset"))}
    assert casts == {
        "clear_noon": True, "cloudy": False, "rain": False, "fog": True, "dusk": True, "night": False, "sunset": True,
    }  # fmt: skip
    road = RoadCurve(np.random.default_rng(3), 300.0)
    night = Renderer(road, weather_named("night"), SMALL, LidarSpec(), 0, 0.0, direct_sunlight=True)
    assert not night.direct_sunlight
    with pytest.raises(ValueError, match="unknown weather 'noon'.*sunset"):
        weather_named("noon")


# sha1 of frames 0 and 120 (rgb, then semantic) of drives of the default benchmark at 96x64, rendered
# before the renderer could cast shadows: training data (seed 0) and the eval benchmark (seed 1).
DEFAULT_FRAMES_SHA1 = {
    (0, "normal", 0): "84026db6cd6e3d5589e56a0640507523cfe71721",  # clear_noon
    (0, "normal", 1): "adc4a60f63b5d82ea675a3cbe51f1b4a61ab8f09",  # cloudy
    (1, "anomalous", 1): "a76a3cb882898afe79dd9d68c0b1a2fab0210cbb",  # clear_noon, animal
}


def test_default_benchmark_frames_are_unchanged():
    for (seed, split, k), expected in DEFAULT_FRAMES_SHA1.items():
        normal, anomalous = (12, 6) if seed == 0 else (0, 12)  # as `umad generate synthetic` and `umad eval` plan them
        plan = [p for p in plan_benchmark(normal, anomalous, seed) if p.split == split][k]
        scenario = SyntheticScenario(plan.seed, 200, plan.anomaly, plan.weather, camera=SMALL)
        digest = hashlib.sha1()
        for i in (0, 120):
            camera = scenario.render(i, with_lidar=False).camera
            digest.update(camera.rgb.tobytes())
            digest.update(camera.semantic.tobytes())
        assert digest.hexdigest() == expected, (
            f"seed {seed} {split} drive {k} ({plan.weather}) renders differently from the shipped benchmark; "
            "the default benchmark may change only with its figures recomputed"
        )
