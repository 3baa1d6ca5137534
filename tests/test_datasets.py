"""Synthetic world and AnoVox I/O: determinism, ground truth, geometry, both layouts, errors."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from umad_common.datasets.anovox import (
    ANOMALY_COLOUR,
    DEPTH_SCALE,
    GENERIC_ANOMALY_TAG,
    AnoVoxScenario,
    decode_depth,
    encode_depth,
    read_pcd,
    write_benchmark_scenario,
    write_pcd,
)
from umad_common.datasets.drive import DatasetError
from umad_common.datasets.formats import find_drives
from umad_common.datasets.synthetic.anomalies import ANOMALY_TAGS, CATEGORIES
from umad_common.datasets.synthetic.generator import generate_benchmark, plan_benchmark
from umad_common.datasets.synthetic.render import WEATHER_NAMES, CameraSpec
from umad_common.datasets.synthetic.scenario import (
    FRAME_DT,
    MAX_ACCEL,
    MAX_DECEL,
    MAX_STEER_RAD,
    WHEELBASE_M,
    SyntheticScenario,
)

SMALL = CameraSpec(width=96, height=64)


def tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha1(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def generated(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth")
    generate_benchmark(out, normal=1, anomalous=1, frames=5, seed=7, size=(96, 64))
    return out


def test_same_seed_gives_identical_bytes(tmp_path, generated):
    generate_benchmark(tmp_path, normal=1, anomalous=1, frames=5, seed=7, size=(96, 64))
    first, second = tree_digest(generated), tree_digest(tmp_path)
    assert len(first) > 5 * 2 * 7 and first == second


def test_scenarios_rendered_in_two_processes_give_the_same_bytes(tmp_path, generated):
    frames_seen = []
    generate_benchmark(
        tmp_path,
        normal=1,
        anomalous=1,
        frames=5,
        seed=7,
        size=(96, 64),
        on_frame=lambda: frames_seen.append(1),
        workers=2,
    )
    assert tree_digest(tmp_path) == tree_digest(generated) and len(frames_seen) == 10


def test_layout_has_generator_folders_and_nonzero_frame_ids(generated):
    folders = find_drives(generated)
    assert [p.parent.name for p in folders] == ["anomalous", "normal"]
    names = {p.name.split("(")[0] for p in folders[0].iterdir()}
    assert {
        "RGB-CAM",
        "DEPTH_CAM",
        "SEMANTIC-CAM",
        "INSTANCE-CAM",
        "LIDAR",
        "ACTION",
        "ANOMALY",
        "ROUTE_MAP",
        "sensor_setup.json",
    } <= names
    scenario = AnoVoxScenario(folders[1])
    assert scenario.layout == "generator" and len(scenario) == 5
    assert scenario.frame_ids[0] > 0 and np.all(np.diff(scenario.frame_ids) == 1)
    assert AnoVoxScenario(folders[1], every=2).frame_ids == scenario.frame_ids[::2]


def test_every_weather_is_in_the_normal_drives():
    plans = plan_benchmark(normal=12, anomalous=6, seed=0)
    assert {p.weather for p in plans if p.split == "normal"} == set(WEATHER_NAMES)
    assert {p.anomaly for p in plans if p.split == "anomalous"} == set(CATEGORIES)
    assert len({p.scenario_id for p in plans}) == 18


def object_in_view(scenario: SyntheticScenario, i: int, max_distance: float) -> tuple[bool, int, int, float]:
    """Whether the anomaly's centre projects into the image (pixel and planar depth)."""
    a = scenario.anomaly
    x, y, heading = scenario.pose(i)
    dx, dy = a.position[0] - x, a.position[1] - y
    fwd = dx * np.cos(heading) + dy * np.sin(heading)
    left = -dx * np.sin(heading) + dy * np.cos(heading)
    up = a.shape.size[2] / 2 - scenario.camera.mount_height
    cam = scenario.camera
    if not 1.0 < fwd < max_distance:
        return False, 0, 0, fwd
    u = int(np.floor(cam.width / 2 - cam.focal * left / fwd))
    v = int(np.floor(cam.height / 2 - cam.focal * up / fwd))
    return (0 <= u < cam.width and 0 <= v < cam.height), u, v, fwd


@pytest.mark.parametrize("category", CATEGORIES)
def test_anomaly_pixels_present_whenever_the_object_is_in_view(category):
    scenario = SyntheticScenario(seed=11, frames=120, anomaly_category=category, camera=SMALL)
    seen = 0
    for i in range(0, 120, 6):
        frame = scenario.renderer.render_camera(scenario.pose(i), scenario.prims_at(i), i)
        visible, u, v, distance = object_in_view(scenario, i, max_distance=30.0)
        anomalous = np.isin(frame.semantic, ANOMALY_TAGS)
        if visible and frame.depth[v, u] > distance - 2.0:  # not hidden behind something nearer
            seen += 1
            assert anomalous.sum() > 0, f"frame {i}: object in view at {distance:.1f} m but no anomaly pixels"
            assert np.all(frame.instance[anomalous] == scenario.anomaly.inst)
        assert np.all(frame.semantic[anomalous] == scenario.anomaly.shape.tag)
    assert seen >= 3


def test_normal_drives_have_no_anomaly_pixels():
    scenario = SyntheticScenario(seed=5, frames=100, camera=SMALL)
    assert scenario.anomaly is None and not np.isin(scenario.static.tag, ANOMALY_TAGS).any()
    for i in range(0, 100, 20):
        frame = scenario.renderer.render_camera(scenario.pose(i), scenario.prims_at(i), i)
        assert not np.isin(frame.semantic, ANOMALY_TAGS).any()


def test_road_depth_matches_the_flat_ground_formula():
    scenario = SyntheticScenario(seed=3, frames=10, camera=SMALL)
    frame = scenario.render(4, with_lidar=False).camera
    cam = scenario.camera
    rows = np.arange(cam.height)[:, None] + 0.5 - cam.height / 2
    road = np.isin(frame.semantic, (1, 24)) & (rows > 0)
    expected = cam.mount_height * cam.focal / np.broadcast_to(rows, road.shape)[road]
    assert road.sum() > 500
    np.testing.assert_allclose(frame.depth[road], expected, rtol=1e-5)


def test_lidar_ranges_agree_with_rendered_depth():
    scenario = SyntheticScenario(seed=9, frames=10, camera=CameraSpec(width=192, height=128))
    frame = scenario.render(5)
    points, cam = frame.lidar, scenario.camera
    assert points.dtype == np.float32 and points.shape[1] == 4
    assert np.linalg.norm(points[:, :3], axis=1).max() <= scenario.lidar.max_range + 1e-3
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    front = x > 2.0
    u = np.floor(cam.width / 2 - cam.focal * y[front] / x[front]).astype(int)
    v = np.floor(cam.height / 2 - cam.focal * z[front] / x[front]).astype(int)
    inside = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    depth = frame.camera.depth[v[inside], u[inside]]
    rel = np.abs(depth - x[front][inside]) / x[front][inside]
    assert inside.sum() > 1000
    assert np.median(rel) < 0.01 and np.mean(rel < 0.05) > 0.9
    ground = np.abs(z + scenario.lidar.mount_height) < 1e-3
    assert ground.sum() > 1000  # flat road returns sit exactly at the mount height below the sensor


def test_ego_actions_follow_curvature_and_motion():
    scenario = SyntheticScenario(seed=23, frames=150, anomaly_category="nature", camera=SMALL)
    t = scenario.track
    np.testing.assert_allclose(
        t.steer, np.clip(-np.arctan(WHEELBASE_M * t.curvature) / MAX_STEER_RAD, -1, 1), atol=1e-9
    )
    poses = np.array([scenario.pose(i) for i in range(150)])
    dheading = np.diff(np.unwrap(poses[:, 2]))
    turning = np.abs(dheading) > 5e-4
    assert turning.sum() > 10 and np.all(np.sign(t.steer[:-1][turning]) == -np.sign(dheading[turning]))
    moving = t.speed[1:] > 0
    accel = np.diff(t.speed) / FRAME_DT
    expected = MAX_ACCEL * t.throttle[:-1] - MAX_DECEL * t.brake[:-1] - 0.02 * t.speed[:-1]
    np.testing.assert_allclose(accel[moving], expected[moving], atol=1e-9)
    step = np.hypot(*np.diff(poses[:, :2], axis=0).T)
    np.testing.assert_allclose(step, 0.5 * (t.speed[1:] + t.speed[:-1]) * FRAME_DT, rtol=0.03, atol=0.02)


def test_loader_reads_what_the_renderer_produced(generated):
    folder = find_drives(generated / "anomalous")[0]
    scenario = AnoVoxScenario(folder)
    plan = next(p for p in plan_benchmark(1, 1, 7) if p.split == "anomalous")
    world = SyntheticScenario(plan.seed, 5, plan.anomaly, plan.weather, camera=SMALL)
    for i in (0, 4):
        frame, truth = scenario[i], world.render(i)
        assert frame.frame_id == plan.first_frame_id + i
        np.testing.assert_array_equal(frame.rgb, truth.camera.rgb)
        np.testing.assert_array_equal(frame.semantic, truth.camera.semantic)
        np.testing.assert_array_equal(frame.instance, truth.camera.instance)
        np.testing.assert_array_equal(frame.anomaly, np.isin(truth.camera.semantic, ANOMALY_TAGS))
        np.testing.assert_allclose(frame.depth, truth.camera.depth, atol=DEPTH_SCALE)
        np.testing.assert_array_equal(frame.lidar, truth.lidar)
        np.testing.assert_array_equal(frame.route, truth.route)
        assert frame.ego.speed_mps == pytest.approx(truth.speed, abs=1e-5)
        assert (frame.ego.throttle, frame.ego.brake, frame.ego.steer) == pytest.approx(
            (truth.throttle, truth.brake, truth.steer), abs=1e-6
        )


@pytest.mark.parametrize("binary", [True, False])
def test_benchmark_layout_reads_the_same_data(tmp_path, generated, binary):
    source = AnoVoxScenario(find_drives(generated / "anomalous")[0])
    written = write_benchmark_scenario(source, tmp_path, source.name, binary_pcd=binary)
    copy = AnoVoxScenario(written)
    assert copy.layout == "benchmark" and copy.frame_ids == source.frame_ids
    for a, b in zip(source, copy, strict=True):
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.anomaly, b.anomaly)
        np.testing.assert_array_equal(np.where(a.anomaly == 1, GENERIC_ANOMALY_TAG, a.semantic), b.semantic)
        np.testing.assert_array_equal(a.lidar, b.lidar)
        assert b.instance is None and b.route is None and b.ego.speed_mps == 0.0
    colour = (tmp_path / source.name / "SEMANTIC_IMG").iterdir().__next__()
    assert colour.suffix == ".png"
    assert any(AnoVoxScenario(written)[i].anomaly.any() for i in range(len(copy))) == any(
        f.anomaly.any() for f in source
    )
    assert ANOMALY_COLOUR == (245, 0, 0)


def test_depth_encoding_round_trip():
    depth = np.array([[0.0, 1.5, 12.25], [99.9, 500.0, 1000.0]], np.float32)
    np.testing.assert_allclose(decode_depth(encode_depth(depth)), depth, atol=DEPTH_SCALE / 2 + 1e-6)
    assert np.all(encode_depth(np.array([[1000.0]])) == 255)


def test_ascii_pcd_without_intensity(tmp_path):
    path = tmp_path / "cloud.pcd"
    path.write_text(
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n1 2 3\n4.5 -5 6\n"
    )
    np.testing.assert_array_equal(read_pcd(path), np.array([[1, 2, 3, 0], [4.5, -5, 6, 0]], np.float32))
    write_pcd(tmp_path / "b.pcd", np.array([[1, 2, 3, 0.5]], np.float32))
    np.testing.assert_array_equal(read_pcd(tmp_path / "b.pcd"), [[1, 2, 3, 0.5]])


def copy_scenario(generated: Path, tmp_path: Path) -> Path:
    import shutil

    source = find_drives(generated / "normal")[0]
    return Path(shutil.copytree(source, tmp_path / source.name))


def sensor_file(folder: Path, prefix: str, index: int) -> Path:
    sensor = next(p for p in folder.iterdir() if p.name.startswith(prefix))
    return sorted(sensor.iterdir())[index]


@pytest.mark.parametrize("prefix", ["DEPTH_CAM", "RGB-CAM", "SEMANTIC-CAM", "LIDAR", "ACTION", "ROUTE_MAP"])
def test_corrupt_file_names_the_file(tmp_path, generated, prefix):
    folder = copy_scenario(generated, tmp_path)
    bad = sensor_file(folder, prefix, 2)
    bad.write_bytes(b"\x89PNG garbage" if bad.suffix != ".csv" else b"frame_id ; 3\nspeed ; fast\n")
    scenario = AnoVoxScenario(folder)
    with pytest.raises(DatasetError, match=bad.name.replace("(", r"\(").replace(")", r"\)")):
        scenario[2]
    scenario[1]  # other frames stay readable


def test_missing_file_names_the_folder_and_frame(tmp_path, generated):
    folder = copy_scenario(generated, tmp_path)
    missing = sensor_file(folder, "SEMANTIC-CAM", 3)
    missing.unlink()
    scenario = AnoVoxScenario(folder)
    with pytest.raises(DatasetError, match=rf"SEMANTIC-CAM.*frame {scenario.frame_ids[3]}"):
        scenario[3]


def test_missing_camera_image_is_a_reported_frame_not_a_gap(tmp_path, generated):
    folder = copy_scenario(generated, tmp_path)
    frames = len(AnoVoxScenario(folder))
    sensor_file(folder, "RGB-CAM", 3).unlink()
    scenario = AnoVoxScenario(folder)
    assert len(scenario) == frames  # the other sensors still recorded frame 3
    with pytest.raises(DatasetError, match=rf"RGB-CAM.*frame {scenario.frame_ids[3]}"):
        scenario[3]
    assert scenario[4].frame_id == scenario.frame_ids[4]


def test_missing_key_and_missing_folders(tmp_path, generated):
    folder = copy_scenario(generated, tmp_path)
    action = sensor_file(folder, "ACTION", 0)
    action.write_text("frame_id ; 1\nthrottle ; 0.5\n")
    with pytest.raises(DatasetError, match="'speed'"):
        AnoVoxScenario(folder)[0]
    with pytest.raises(DatasetError, match="no camera folder"):
        AnoVoxScenario(tmp_path)
    with pytest.raises(DatasetError, match="no such folder"):
        find_drives(tmp_path / "nowhere")
    assert find_drives(generated / "Scenario_Configuration_Files") == []


def test_cli_writes_benchmark_and_preview(tmp_path):
    from umad_common.cli import main

    args = [
        "generate",
        "synthetic",
        str(tmp_path),
        "--normal",
        "1",
        "--anomalous",
        "1",
        "--frames",
        "3",
        "--size",
        "64x48",
    ]
    assert main([*args, "--preview", "--seed", "2"]) == 0
    assert (tmp_path / "preview.png").is_file()
    assert (tmp_path / "Scenario_Configuration_Files" / "scenario_config_map_Synthetic.json").is_file()
    assert AnoVoxScenario(find_drives(tmp_path / "normal")[0])[0].rgb.shape == (48, 64, 3)
    assert main(args) == 2  # refuses to write into a folder that already holds scenarios
    with pytest.raises(SystemExit):
        main(["generate", "synthetic", str(tmp_path / "x"), "--size", "64by48"])


def test_stress_plans_cover_the_weathers_unevenly_and_leave_the_default_plans_alone():
    from umad_common.datasets.synthetic.generator import STRESS, stress_coverage

    plans = plan_benchmark(12, 8, STRESS.seed, stress=STRESS)
    normal = [p.weather for p in plans if p.split == "normal"]
    anomalous = [p for p in plans if p.split == "anomalous"]
    counts = {w: normal.count(w) for w in WEATHER_NAMES}
    assert counts == stress_coverage(STRESS, 12, 8)["normal"]
    assert counts["clear_noon"] == 0 and counts["dusk"] == 1 and counts["night"] == 1 and max(counts.values()) >= 4
    rare = {w for w, n in counts.items() if n <= 1}
    assert sum(p.weather in rare for p in anomalous) > len(anomalous) / 2  # mostly under rare presets...
    assert any(p.weather not in rare for p in anomalous)  # ...among others
    assert all(p.anomaly is not None for p in anomalous)
    default = plan_benchmark(12, 6, 0)
    assert {p.weather for p in default if p.split == "normal"} == set(WEATHER_NAMES)
    assert not {p.scenario_id for p in default} & {p.scenario_id for p in plans}


def test_stress_drive_stops_far_before_the_object_and_waits_to_the_end():
    from umad_common.datasets.synthetic.generator import STRESS_WAIT_M

    for seed, category in ((1, "home"), (2, "animal"), (3, "nature")):
        scenario = SyntheticScenario(seed, 200, category, "dusk", camera=SMALL, wait_at=STRESS_WAIT_M)
        track, anomaly = scenario.track, scenario.anomaly
        assert anomaly.behaviour == "brake"
        still = np.flatnonzero(track.speed < 0.05)
        assert still.size and still[0] < 70, f"seed {seed}: standing still from frame {still[:1]}, expected < 70"
        assert np.all(track.speed[still[0] :] < 0.05), "the ego must wait to the end of the drive"
        gap = anomaly.s - max(anomaly.shape.size[:2]) / 2 - track.s[-1]
        assert 19.0 <= gap <= 41.0, f"seed {seed}: the ego stops {gap:.1f} m before the object, expected 20-40"
    with pytest.raises(ValueError, match="wait_at"):
        SyntheticScenario(1, 10, "home", camera=SMALL, wait_at=(30.0, 20.0))


def test_cli_writes_the_stress_set(tmp_path):
    import json

    from umad_common.cli import main

    args = ["generate", "synthetic", str(tmp_path), "--stress", "--normal", "2", "--anomalous", "1"]
    assert main([*args, "--frames", "2", "--size", "64x48"]) == 0
    config = json.loads((tmp_path / "Scenario_Configuration_Files" / "scenario_config_map_Synthetic.json").read_text())
    assert config["set"] == "stress" and config["seed"] == 30 and config["wait_m"] == [20.0, 40.0]
    assert [s["weather"] for s in config["scenarios"]] == ["cloudy", "fog", "clear_noon"]
    assert len(find_drives(tmp_path / "normal")) == 2 and len(find_drives(tmp_path / "anomalous")) == 1


def test_light_stress_plans_show_clear_light_rarely_in_normal_drives_and_always_in_anomalous_ones():
    from umad_common.datasets.synthetic.generator import STRESS, STRESS_LIGHT, stress_coverage

    clear = {"clear_noon", "sunset"}
    plans = plan_benchmark(16, 8, STRESS_LIGHT.seed, stress=STRESS_LIGHT)
    normal = [p.weather for p in plans if p.split == "normal"]
    anomalous = [p for p in plans if p.split == "anomalous"]
    assert sum(w in clear for w in normal) == 3 and {"clear_noon", "sunset"} <= set(normal)
    assert len(set(normal) - clear) >= 5  # cloudy, fog, rain, dusk, night
    assert len(anomalous) == 8 and all(p.weather in clear and p.anomaly is not None for p in anomalous)
    assert {p.weather for p in anomalous} == clear
    assert stress_coverage(STRESS_LIGHT, 16, 8)["normal"] == {w: normal.count(w) for w in (*WEATHER_NAMES, "sunset")}
    assert "sunset" not in stress_coverage(STRESS, 12, 8)["normal"]  # the stress set's config stays as it was
    for seed in (STRESS_LIGHT.seed, 44):  # the default and the validation seed give other drives than every other set
        ids = {p.scenario_id for p in plan_benchmark(16, 8, seed, stress=STRESS_LIGHT)}
        assert not ids & {p.scenario_id for p in plan_benchmark(12, 6, 0)}
        assert not ids & {p.scenario_id for p in plan_benchmark(0, 12, 1)}
        assert not ids & {p.scenario_id for p in plan_benchmark(12, 8, STRESS.seed, stress=STRESS)}


def test_light_stress_drive_waits_before_the_object_facing_the_sun():
    from umad_common.datasets.synthetic.generator import STRESS_WAIT_M
    from umad_common.datasets.synthetic.scenario import SUN_AHEAD_DEG

    for seed, category, weather in ((4, "home", "sunset"), (5, "special", "clear_noon")):
        scenario = SyntheticScenario(
            seed, 200, category, weather, camera=SMALL, wait_at=STRESS_WAIT_M, direct_sunlight=True, sun_ahead=True
        )
        track, anomaly = scenario.track, scenario.anomaly
        still = np.flatnonzero(track.speed < 0.05)
        assert still.size and np.all(track.speed[still[0] :] < 0.05), "the ego must wait to the end of the drive"
        gap = anomaly.s - max(anomaly.shape.size[:2]) / 2 - track.s[-1]
        assert 19.0 <= gap <= 41.0, f"seed {seed}: the ego stops {gap:.1f} m before the object, expected 20-40"
        sun = scenario.renderer.sun
        off = np.degrees(np.abs(np.angle(np.exp(1j * (np.arctan2(sun[1], sun[0]) - scenario.pose(199)[2])))))
        assert SUN_AHEAD_DEG[0] - 1e-6 <= off <= SUN_AHEAD_DEG[1] + 1e-6, f"seed {seed}: sun {off:.1f} deg off ahead"
        assert scenario.renderer.direct_sunlight


def test_cli_writes_the_light_stress_set(tmp_path):
    import json

    from umad_common.cli import main

    args = ["generate", "synthetic", str(tmp_path), "--stress-light", "--normal", "5", "--anomalous", "2"]
    assert main([*args, "--frames", "2", "--size", "64x48", "--preview"]) == 0
    config = json.loads((tmp_path / "Scenario_Configuration_Files" / "scenario_config_map_Synthetic.json").read_text())
    assert config["set"] == "stress_light" and config["seed"] == 43 and config["wait_m"] == [20.0, 40.0]
    assert config["direct_sunlight"] is True and config["weather_drives"]["anomalous"]["sunset"] == 1
    assert [s["weather"] for s in config["scenarios"]] == [
        "cloudy",
        "fog",
        "rain",
        "dusk",
        "clear_noon",
        "sunset",
        "clear_noon",
    ]
    assert (tmp_path / "preview.png").is_file()
    from umad_common.datasets.anovox import scenario_weathers

    weathers = scenario_weathers(find_drives(tmp_path / "anomalous")[0])  # what per_scenario.md names
    assert weathers == {f"Scenario_{s['scenario_id']}": s["weather"] for s in config["scenarios"]}
    with pytest.raises(SystemExit):
        main(["generate", "synthetic", str(tmp_path / "x"), "--stress", "--stress-light"])


def test_facades_stress_plans_show_night_and_the_low_sun_rarely_in_normal_drives_and_always_in_anomalous_ones():
    from umad_common.datasets.synthetic.generator import STRESS, STRESS_FACADES, STRESS_LIGHT, stress_coverage

    plans = plan_benchmark(16, 8, STRESS_FACADES.seed, stress=STRESS_FACADES)
    normal = [p.weather for p in plans if p.split == "normal"]
    anomalous = [p for p in plans if p.split == "anomalous"]
    assert normal.count("night") == 1 and normal.count("sunset") == 1
    assert sum(w in {"cloudy", "fog", "rain", "dusk"} for w in normal) == 12  # most under overcast, fog, rain, dusk
    assert [p.weather for p in anomalous] == ["night", "sunset"] * 4 and all(p.anomaly is not None for p in anomalous)
    assert stress_coverage(STRESS_FACADES, 16, 8)["normal"] == {w: normal.count(w) for w in (*WEATHER_NAMES, "sunset")}
    assert STRESS_FACADES.seed == 47 and STRESS_FACADES.sun_side and not STRESS_FACADES.sun_ahead
    assert STRESS_FACADES.direct_sunlight and STRESS_FACADES.built_up and STRESS_FACADES.pole_spacing is not None
    for other in (STRESS, STRESS_LIGHT):  # the other sets keep their worlds and light
        assert not other.sun_side and other.pole_spacing is None and not other.built_up
    for seed in (STRESS_FACADES.seed, 48):  # the default and the validation seed give other drives than every other set
        ids = {p.scenario_id for p in plan_benchmark(16, 8, seed, stress=STRESS_FACADES)}
        assert not ids & {p.scenario_id for p in plan_benchmark(12, 6, 0)}
        assert not ids & {p.scenario_id for p in plan_benchmark(0, 12, 1)}
        assert not ids & {p.scenario_id for p in plan_benchmark(12, 8, STRESS.seed, stress=STRESS)}
        for light_seed in (STRESS_LIGHT.seed, 44):
            assert not ids & {p.scenario_id for p in plan_benchmark(16, 8, light_seed, stress=STRESS_LIGHT)}


def _pole_instances(scenario: SyntheticScenario) -> dict[int, float]:
    """Pole-only instances (bare poles, lamps' and signs' poles) of the static world: id -> |d| of the pole."""
    from umad_common.datasets.synthetic.world import KIND_CYLINDER, TAG_POLE

    prims = scenario.static
    upright = (prims.kind == KIND_CYLINDER) & (prims.tag == TAG_POLE)
    _, d = scenario.road.to_road(prims.center[upright, 0], prims.center[upright, 1])
    return dict(zip(prims.inst[upright].tolist(), np.abs(d).tolist(), strict=True))


def test_facades_stress_world_has_a_row_of_thin_poles_and_sunlit_facades():
    from umad_common.datasets.synthetic.generator import STRESS_FACADES, STRESS_WAIT_M
    from umad_common.datasets.synthetic.scenario import SUN_SIDE_DEG
    from umad_common.datasets.synthetic.world import POLE_ROW_D, TAG_BUILDING

    for seed, category, weather in ((4, "home", "sunset"), (6, "animal", "night")):
        kwargs = dict(camera=SMALL, wait_at=STRESS_WAIT_M, direct_sunlight=True)
        plain = SyntheticScenario(seed, 200, category, weather, **kwargs)
        facades = SyntheticScenario(
            seed,
            200,
            category,
            weather,
            **kwargs,
            sun_side=True,
            pole_spacing=STRESS_FACADES.pole_spacing,
            built_up=True,
        )
        before, after = _pole_instances(plain), _pole_instances(facades)
        row = [d for d in after.values() if abs(d - POLE_ROW_D) < 0.2]
        length = facades.track.s[-1] + 230.0  # the world spans s = -60 .. s_end + 170
        assert len(after) >= 2 * len(before), f"seed {seed}: {len(after)} poles against {len(before)}"
        assert len(row) >= 2 * length / STRESS_FACADES.pole_spacing[1] * 0.8, f"seed {seed}: {len(row)} in the row"
        assert facades.style.name in ("urban", "suburban")
        track, anomaly = facades.track, facades.anomaly
        still = np.flatnonzero(track.speed < 0.05)
        assert still.size and np.all(track.speed[still[0] :] < 0.05), "the ego must wait to the end of the drive"
        gap = anomaly.s - max(anomaly.shape.size[:2]) / 2 - track.s[-1]
        assert 19.0 <= gap <= 41.0, f"seed {seed}: the ego stops {gap:.1f} m before the object, expected 20-40"
        sun = facades.renderer.sun
        off = np.degrees(np.abs(np.angle(np.exp(1j * (np.arctan2(sun[1], sun[0]) - facades.pose(199)[2])))))
        assert SUN_SIDE_DEG[0] - 1e-6 <= off <= SUN_SIDE_DEG[1] + 1e-6, f"seed {seed}: sun {off:.1f} deg off ahead"
    with pytest.raises(ValueError, match="exclude"):
        SyntheticScenario(1, 10, "home", camera=SMALL, sun_ahead=True, sun_side=True)
    # The low sun to the side lights the facades beside the road (their brightest tenth) more than the same sun ahead.
    lit = {}
    for where in ("sun_side", "sun_ahead"):
        scenario = SyntheticScenario(
            5, 200, "home", "sunset", camera=SMALL, wait_at=STRESS_WAIT_M, direct_sunlight=True, built_up=True,
            **{where: True},
        )  # fmt: skip
        frame = scenario.render(199, with_lidar=False).camera
        building = frame.semantic == TAG_BUILDING
        assert building.mean() > 0.05
        lit[where] = float(np.percentile(frame.rgb[building].mean(axis=1), 90))
    assert lit["sun_side"] > 1.5 * lit["sun_ahead"], lit


def test_cli_writes_the_facades_stress_set_the_same_twice(tmp_path):
    import json

    from umad_common.cli import main

    args = ["--stress-facades", "--normal", "2", "--anomalous", "2", "--frames", "2", "--size", "64x48"]
    assert main(["generate", "synthetic", str(tmp_path / "a"), *args, "--preview"]) == 0
    assert main(["generate", "synthetic", str(tmp_path / "b"), *args, "--workers", "1"]) == 0

    def digests(root: Path) -> dict[str, str]:
        files = sorted(p for p in root.rglob("*") if p.is_file() and p.name != "preview.png")
        return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in files}

    first = digests(tmp_path / "a")
    assert len(first) > 20 and first == digests(tmp_path / "b")
    config = json.loads(
        (tmp_path / "a" / "Scenario_Configuration_Files" / "scenario_config_map_Synthetic.json").read_text()
    )
    assert config["set"] == "stress_facades" and config["seed"] == 47 and config["wait_m"] == [20.0, 40.0]
    assert config["direct_sunlight"] is True and config["built_up"] is True and config["pole_spacing_m"] == [6.0, 10.0]
    assert config["sun_side_deg"] == [95.0, 125.0] and config["sun_ahead_in_anomalous_drives"] is False
    assert [s["weather"] for s in config["scenarios"]] == ["cloudy", "fog", "night", "sunset"]
    assert all(s["style"] != "rural" for s in config["scenarios"])
    assert (tmp_path / "a" / "preview.png").is_file()
    with pytest.raises(SystemExit):
        main(["generate", "synthetic", str(tmp_path / "x"), "--stress-light", "--stress-facades"])
