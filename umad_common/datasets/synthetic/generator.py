"""Writes synthetic drives in the AnoVox generator layout, and a preview contact sheet.

Output is a pure function of the arguments: scenario seeds, folder uuids and first frame ids come
from one seeded generator, PNGs are written by cv2 (deterministic zlib), files carry no timestamps.
Normal drives cycle through every weather preset, so a model trained on them has seen each one.

The stress sets (`stress=STRESS`, `STRESS_LIGHT` or `STRESS_FACADES`, each with its own default
seed) are what the default benchmark never shows. STRESS: normal drives that cover the presets unevenly
(STRESS_NORMAL_WEATHERS: some in one drive of twelve, clear_noon in none) and anomalous drives,
mostly under those rare presets, in which the ego brakes early to stand 20-40 m before the object
and waits there to the end of the drive. STRESS_LIGHT: the direct sun (cast shadows, lane glare) in
every drive whose sun shows, clear light (clear_noon, sunset) in 3 of 16 normal drives, and
anomalous drives all under clear light, the ego waiting 20-40 m before the object facing the sun.
STRESS_FACADES: the light that fails the maps elsewhere, sunlit facades and thin poles. Every drive
is built up (no rural ones) with a row of bare thin poles along each sidewalk by the curb, the sun
(direct, cast shadows) to the side and a little behind where the drive ends; normal drives cover the
presets as the light set's do (night 1, sunset 1 of 16), anomalous drives alternate night and
sunset (a low sun lighting the facades beside the road), the ego waiting 20-40 m before the object.
Seeds 44 (light) and 48 (facades) are validation seeds that `umad eval` never evaluates.
"""

from __future__ import annotations

import hashlib
import json
import uuid
from collections.abc import Callable
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from umad_common.datasets.anovox import KMH_PER_MPS, AnoVoxScenario, encode_depth, semantic_to_colour, write_key_values
from umad_common.datasets.synthetic.anomalies import CATEGORIES
from umad_common.datasets.synthetic.render import EXTRA_WEATHERS, WEATHER_NAMES, CameraSpec, LidarSpec
from umad_common.datasets.synthetic.scenario import SUN_SIDE_DEG, SyntheticScenario

MOUNT = "(0, 0, 1.8)(0, 0, 0)"
STRESS_SEED = 30  # the stress set's default master seed
# Normal drives of the stress set cycle through these twelve: cloudy 5, fog 3, rain 2, dusk 1,
# night 1, clear_noon 0 (any four drives already hold dusk once).
STRESS_NORMAL_WEATHERS = (
    "cloudy", "fog", "rain", "dusk", "cloudy", "fog", "rain", "cloudy", "fog", "cloudy", "night", "cloudy",
)  # fmt: skip
# Anomalous drives of the stress set cycle through these eight: mostly the rare and unseen presets,
# with fog, rain and cloudy (well covered) as controls.
STRESS_ANOMALOUS_WEATHERS = ("clear_noon", "dusk", "fog", "night", "clear_noon", "dusk", "rain", "cloudy")
STRESS_WAIT_M = (20.0, 40.0)  # gap between the stopped ego and the object in the stress sets' anomalous drives
STRESS_LIGHT_SEED = 43  # the light stress set's default master seed (choose on seed 44: docs/benchmarks.md)
# Normal drives of the light stress set cycle through these sixteen: clear light (clear_noon 2,
# sunset 1) in three, cloudy 5, fog 3, rain 2, dusk 2, night 1.
STRESS_LIGHT_NORMAL_WEATHERS = (
    "cloudy", "fog", "rain", "dusk", "clear_noon", "cloudy", "fog", "night",
    "cloudy", "sunset", "rain", "dusk", "cloudy", "fog", "clear_noon", "cloudy",
)  # fmt: skip
STRESS_LIGHT_ANOMALOUS_WEATHERS = ("sunset", "clear_noon")  # anomalous drives alternate these
STRESS_FACADES_SEED = 47  # the facades stress set's default master seed (choose on seed 48)
# Normal drives of the facades stress set cycle through these sixteen, as the light set's cover the
# presets: cloudy 5, fog 3, rain 2, dusk 2, clear_noon 2, night 1, sunset 1 (the side-lit low sun).
STRESS_FACADES_NORMAL_WEATHERS = (
    "cloudy", "fog", "rain", "dusk", "cloudy", "clear_noon", "fog", "night",
    "cloudy", "rain", "sunset", "dusk", "cloudy", "fog", "clear_noon", "cloudy",
)  # fmt: skip
STRESS_FACADES_ANOMALOUS_WEATHERS = ("night", "sunset")  # anomalous drives alternate these
STRESS_FACADES_POLE_SPACING_M = (6.0, 10.0)  # the bare poles' row (lamps stand 26-36 m apart, signs 60-140 m)
PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 3]
EGO_TYPE = "vehicle.lincoln.mkz_2020"


@dataclass(frozen=True)
class StressSet:
    """A set of drives the default benchmark never shows: its weather cycles and how it is lit."""

    name: str  # the config file's "set"
    seed: int  # default master seed
    normal_weathers: tuple[str, ...]  # normal drives cycle through these presets...
    anomalous_weathers: tuple[str, ...]  # ...and anomalous ones through these
    direct_sunlight: bool  # cast shadows and lane glare in every drive whose sun shows
    sun_ahead: bool  # the sun stands ahead of where the anomalous drives' ego waits
    sun_side: bool = False  # the sun stands to the side of where every drive ends (lights the facades)
    pole_spacing: tuple[float, float] | None = None  # metres between bare thin poles by the curb; None: none
    built_up: bool = False  # no rural drives (their draw gives suburban ones)


STRESS = StressSet("stress", STRESS_SEED, STRESS_NORMAL_WEATHERS, STRESS_ANOMALOUS_WEATHERS, False, False)
STRESS_LIGHT = StressSet(
    "stress_light", STRESS_LIGHT_SEED, STRESS_LIGHT_NORMAL_WEATHERS, STRESS_LIGHT_ANOMALOUS_WEATHERS, True, True
)
STRESS_FACADES = StressSet(
    "stress_facades",
    STRESS_FACADES_SEED,
    STRESS_FACADES_NORMAL_WEATHERS,
    STRESS_FACADES_ANOMALOUS_WEATHERS,
    direct_sunlight=True,
    sun_ahead=False,
    sun_side=True,
    pole_spacing=STRESS_FACADES_POLE_SPACING_M,
    built_up=True,
)


@dataclass(frozen=True)
class ScenarioPlan:
    """What one scenario of a generated benchmark is, fixed before anything is rendered."""

    split: str  # "normal" or "anomalous"
    scenario_id: str  # uuid4 string
    seed: int
    weather: str
    anomaly: str | None  # AnoVox category or None
    first_frame_id: int


def plan_benchmark(normal: int, anomalous: int, seed: int, stress: StressSet | None = None) -> list[ScenarioPlan]:
    """Scenario plans: normal drives cycle through all weathers; anomalous ones through categories
    and weathers. With a `stress` set, weathers cycle through its presets instead."""
    if stress is not None:
        return _plan_stress(normal, anomalous, seed, stress)
    rng = np.random.default_rng(seed)
    plans = []
    for split, count in (("normal", normal), ("anomalous", anomalous)):
        for k in range(count):
            scenario_id = str(uuid.UUID(bytes=rng.bytes(16), version=4))
            scenario_seed = int(rng.integers(2**31))
            first = int(rng.integers(1_000, 60_000))
            weather = (
                WEATHER_NAMES[k % len(WEATHER_NAMES)]
                if split == "normal"
                else WEATHER_NAMES[(k * 5 + 1) % len(WEATHER_NAMES)]
            )
            category = CATEGORIES[k % len(CATEGORIES)] if split == "anomalous" else None
            plans.append(ScenarioPlan(split, scenario_id, scenario_seed, weather, category, first))
    return plans


def _plan_stress(normal: int, anomalous: int, seed: int, stress: StressSet) -> list[ScenarioPlan]:
    rng = np.random.default_rng(seed)
    plans = []
    for split, count, weathers in (
        ("normal", normal, stress.normal_weathers),
        ("anomalous", anomalous, stress.anomalous_weathers),
    ):
        for k in range(count):
            scenario_id = str(uuid.UUID(bytes=rng.bytes(16), version=4))
            scenario_seed = int(rng.integers(2**31))
            first = int(rng.integers(1_000, 60_000))
            category = CATEGORIES[k % len(CATEGORIES)] if split == "anomalous" else None
            plans.append(ScenarioPlan(split, scenario_id, scenario_seed, weathers[k % len(weathers)], category, first))
    return plans


def stress_coverage(stress: StressSet, normal: int, anomalous: int) -> dict[str, dict[str, int]]:
    """Drives per weather preset of a stress set of this size: {"normal": {...}, "anomalous": {...}}
    (every preset of the default cycle, and the extra presets the set uses)."""
    used = {*stress.normal_weathers, *stress.anomalous_weathers}
    names = [*WEATHER_NAMES, *(w.name for w in EXTRA_WEATHERS if w.name in used)]
    return {
        split: {w: sum(weathers[k % len(weathers)] == w for k in range(count)) for w in names}
        for split, count, weathers in (
            ("normal", normal, stress.normal_weathers),
            ("anomalous", anomalous, stress.anomalous_weathers),
        )
    }


def sensor_setup(camera: CameraSpec, lidar: LidarSpec) -> dict[str, dict]:
    """sensor_setup.json content keyed by the sensor folder name `<TYPE>(loc)(rot)_<hash>`."""
    cam_args = {"image_size_x": camera.width, "image_size_y": camera.height, "fov": camera.fov_deg}
    lidar_args = {
        "channels": lidar.channels, "upper_fov": lidar.upper_deg, "lower_fov": lidar.lower_deg, "range": lidar.max_range,
        "points_per_second": lidar.channels * lidar.azimuth_bins * 10, "rotation_frequency": 10,
    }  # fmt: skip
    sensors = {
        "RGB-CAM": ("sensor.camera.rgb", "png", cam_args),
        "DEPTH_CAM": ("sensor.camera.depth", "png", cam_args),
        "SEMANTIC-CAM": ("sensor.camera.semantic_segmentation", "png", cam_args),
        "INSTANCE-CAM": ("sensor.camera.instance_segmentation", "png", cam_args),
        "LIDAR": ("sensor.lidar.ray_cast", "npy", lidar_args),
    }
    setup = {}
    for kind, (sensor_type, ending, args) in sensors.items():
        digest = hashlib.sha1(json.dumps([sensor_type, args], sort_keys=True).encode()).hexdigest()[:8]
        setup[f"{kind}{MOUNT}_{digest}"] = {
            "sensor_type": sensor_type, "location": [0, 0, 1.8], "rotation": [0, 0, 0],
            "file_ending": ending, "args": args, "save_data": True,
        }  # fmt: skip
    return setup


def _carla_triplet(x: float, y: float, z: float) -> str:
    """A world vector in CARLA's left-handed axes (y to the right)."""
    return f"({x:.4f}, {-y:.4f}, {z:.4f})"


def write_scenario(
    scenario: SyntheticScenario, plan: ScenarioPlan, out_dir: Path, on_frame: Callable[[], None] | None = None
) -> Path:
    """Render every frame of a scenario and write it as `out_dir/Scenario_<uuid>/` (generator layout)."""
    root = out_dir / f"Scenario_{plan.scenario_id}"
    setup = sensor_setup(scenario.camera, scenario.lidar)
    folders = {name.split("(")[0]: root / name for name in setup}
    for folder in [*folders.values(), root / "ACTION", root / "ROUTE_MAP"] + (
        [root / "ANOMALY"] if scenario.anomaly else []
    ):
        folder.mkdir(parents=True, exist_ok=False)
    (root / "sensor_setup.json").write_text(json.dumps(setup, indent=2, sort_keys=True) + "\n")
    for i in range(scenario.frames):
        fid = plan.first_frame_id + i
        frame = scenario.render(i)
        cam = frame.camera
        paths = {kind: str(folder / f"{folder.name}_{fid}") for kind, folder in folders.items()}
        cv2.imwrite(paths["RGB-CAM"] + ".png", cam.rgb[..., ::-1], PNG_PARAMS)
        cv2.imwrite(paths["DEPTH_CAM"] + ".png", encode_depth(cam.depth), PNG_PARAMS)
        cv2.imwrite(paths["SEMANTIC-CAM"] + ".png", cam.semantic, PNG_PARAMS)
        ids = cam.instance  # R = tag, G = id low byte, B = id high byte (cv2 writes BGR)
        instance_bgr = np.stack([(ids >> 8) & 255, ids & 255, cam.semantic], axis=-1).astype(np.uint8)
        cv2.imwrite(paths["INSTANCE-CAM"] + ".png", instance_bgr, PNG_PARAMS)
        np.save(paths["LIDAR"] + ".npy", frame.lidar)
        cv2.imwrite(str(root / "ROUTE_MAP" / f"ROUTE_MAP_{fid}.png"), frame.route, PNG_PARAMS)
        x, y, heading = frame.pose
        write_key_values(root / "ACTION" / f"ACTION_{fid}.csv", {
            "frame_id": fid, "scenario_id": plan.scenario_id, "vehicle_id": 1, "vehicle_type_id": EGO_TYPE,
            "speed": f"{frame.speed * KMH_PER_MPS:.6f}", "throttle": f"{frame.throttle:.6f}", "steer": f"{frame.steer:.6f}",
            "brake": f"{frame.brake:.6f}", "hand_brake": False, "reverse": False, "gear": 1 if frame.speed > 0 else 0,
            "location": _carla_triplet(x, y, 0.0), "rotation": f"(0.0000, {-np.degrees(heading):.4f}, 0.0000)",
        })  # fmt: skip
        if scenario.anomaly is not None:
            a = scenario.anomaly
            write_key_values(root / "ANOMALY" / f"ANOMALY_{fid}.csv", {
                "frame_id": fid, "scenario_id": plan.scenario_id, "anomaly_id": a.inst, "anomaly_type_id": a.shape.type_id,
                "anomaly_is_alive": True, "semantic_tags": f"[{a.shape.tag}]", "location": _carla_triplet(*a.position),
                "rotation": f"(0.0000, {-np.degrees(a.yaw):.4f}, 0.0000)", "velocity": "(0.0000, 0.0000, 0.0000)",
                "acceleration": "(0.0000, 0.0000, 0.0000)", "size": "({:.4f}, {:.4f}, {:.4f})".format(*a.shape.size),
                "behaviour": a.behaviour,
            })  # fmt: skip
        if on_frame is not None:
            on_frame()
    return root


def scenario_record(plan: ScenarioPlan, scenario: SyntheticScenario) -> dict:
    """One entry of Scenario_Configuration_Files/scenario_config_map_Synthetic.json."""
    record = asdict(plan) | {
        "frames": scenario.frames,
        "style": scenario.style.name,
        "image_size": [scenario.camera.width, scenario.camera.height],
    }
    if scenario.anomaly is not None:
        a = scenario.anomaly
        record |= {"anomaly_type_id": a.shape.type_id, "anomaly_tag": a.shape.tag, "behaviour": a.behaviour}
    return record


def generate_benchmark(
    out: Path,
    normal: int,
    anomalous: int,
    frames: int,
    seed: int,
    size: tuple[int, int],
    on_frame: Callable[[], None] | None = None,
    stress: StressSet | None = None,
    workers: int = 1,
) -> list[Path]:
    """Write OUT/normal/Scenario_*, OUT/anomalous/Scenario_* and the scenario config file; with a
    `stress` set (see the module docstring), that set for the same arguments. Each scenario is
    rendered from its own seed, so `workers` > 1 renders scenarios in that many processes and writes
    the same bytes (`on_frame` is then called for a scenario's frames when it is done)."""
    camera = CameraSpec(width=size[0], height=size[1])
    render = partial(_render_scenario, frames=frames, camera=camera, out=out, stress=stress)
    plans = plan_benchmark(normal, anomalous, seed, stress)
    if workers > 1 and len(plans) > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        done = []
        with ProcessPoolExecutor(min(workers, len(plans)), mp_context=multiprocessing.get_context("spawn")) as pool:
            for result in pool.map(render, plans):
                done.append(result)
                if on_frame is not None:
                    for _ in range(frames):
                        on_frame()
    else:
        done = [render(plan, on_frame=on_frame) for plan in plans]
    roots, records = [root for root, _ in done], [record for _, record in done]
    config_dir = out / "Scenario_Configuration_Files"
    config_dir.mkdir(parents=True, exist_ok=True)
    (config_dir / "scenario_config_map_Synthetic.json").write_text(
        json.dumps(
            {"seed": seed, "scenarios": records, **_stress_note(stress, normal, anomalous)}, indent=2, sort_keys=True
        )
        + "\n"
    )
    return roots


def _render_scenario(
    plan: ScenarioPlan,
    frames: int,
    camera: CameraSpec,
    out: Path,
    stress: StressSet | None,
    on_frame: Callable[[], None] | None = None,
) -> tuple[Path, dict]:
    """Render and write one planned scenario; (its folder, its config record)."""
    scenario = SyntheticScenario(
        plan.seed,
        frames,
        plan.anomaly,
        plan.weather,
        camera=camera,
        wait_at=STRESS_WAIT_M if stress is not None else None,
        direct_sunlight=stress is not None and stress.direct_sunlight,
        sun_ahead=stress is not None and stress.sun_ahead and plan.anomaly is not None,
        sun_side=stress is not None and stress.sun_side,
        pole_spacing=stress.pole_spacing if stress is not None else None,
        built_up=stress is not None and stress.built_up,
    )
    (out / plan.split).mkdir(parents=True, exist_ok=True)
    return write_scenario(scenario, plan, out / plan.split, on_frame), scenario_record(plan, scenario)


def _stress_note(stress: StressSet | None, normal: int, anomalous: int) -> dict:
    """What the config file adds for a stress set (nothing for the default benchmark)."""
    if stress is None:
        return {}
    note = {
        "set": stress.name,
        "wait_m": list(STRESS_WAIT_M),
        "weather_drives": stress_coverage(stress, normal, anomalous),
    }
    if stress.direct_sunlight:
        note |= {"direct_sunlight": True, "sun_ahead_in_anomalous_drives": stress.sun_ahead}
    if stress.sun_side:
        note |= {"sun_side_deg": list(SUN_SIDE_DEG)}
    if stress.pole_spacing is not None:
        note |= {"pole_spacing_m": list(stress.pole_spacing)}
    if stress.built_up:
        note |= {"built_up": True}
    return note


def _label(image: np.ndarray, text: str) -> np.ndarray:
    out = image.copy()
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def write_preview(scenario_dirs: list[Path], path: Path, rows: int = 6) -> None:
    """Contact sheet, one row per scenario: rgb | semantic (CARLA colours) | depth | anomaly overlay.

    Anomalous rows show the sampled frame with the most anomaly pixels."""
    normal = [d for d in scenario_dirs if d.parent.name == "normal"][: rows // 2]
    anomalous = [d for d in scenario_dirs if d.parent.name == "anomalous"][: rows - len(normal)]
    lines = []
    for folder in normal + anomalous:
        scenario = AnoVoxScenario(folder)
        candidates = [scenario[int(len(scenario) * q)] for q in (0.3, 0.5, 0.7, 0.9)]
        frame = max(candidates, key=lambda f: int(f.anomaly.sum())) if folder in anomalous else candidates[1]
        depth = np.log(np.clip(frame.depth, 1, 1000)) / np.log(1000)
        depth_bgr = cv2.applyColorMap(np.round(255 * (1 - depth)).astype(np.uint8), cv2.COLORMAP_MAGMA)
        overlay = frame.rgb[..., ::-1].astype(np.float64)
        mask = frame.anomaly.astype(bool)
        overlay[mask] = 0.4 * overlay[mask] + 0.6 * np.array([0, 0, 255])
        title = f"{folder.parent.name} {folder.name[:17]} frame {frame.frame_id}"
        cells = [
            _label(frame.rgb[..., ::-1], title),
            semantic_to_colour(frame.semantic)[..., ::-1],
            depth_bgr,
            _label(overlay.astype(np.uint8), f"anomaly px {int(mask.sum())}"),
        ]
        lines.append(np.concatenate(cells, axis=1))
    cv2.imwrite(str(path), np.concatenate(lines, axis=0), PNG_PARAMS)
