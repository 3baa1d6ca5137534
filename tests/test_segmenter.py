"""The segmenter operator and its methods: output contract on frames that look like the built-in
world's, ground truth masks from instance ids, the registry (a user's `package.module:Class`), the
`geometry` method on hand-made lidar clouds, and the `sam` method's errors at construction (main
environment; the end-to-end SAM run is tests/test_sam.py)."""

from __future__ import annotations

import json
import sys
import textwrap

import numpy as np
import pytest
from pydantic import ValidationError

from umad_common.dataflow import Context, Frame
from umad_common.dataflow.api.messages import Message
from umad_common.refine import resize_nearest
from umad_common.segmentation import SEGMENTERS, connected_regions, labels_to_masks
from umad_operators.segmenter import Segmenter

H, W = 128, 192  # world model size
FULL_H, FULL_W = 256, 384  # synthetic world render size
SKY, ROAD, BUILDING, MARKING, CAR, ANOMALY = 1, 2, 3, 4, 5, 6


def driving_scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A synthetic-world-like frame at render size: sky, buildings, road with lane marks, a car and
    an anomaly (each object its own instance id). Returns rgb (H,W,3) float32, instance, semantic."""
    rng = np.random.default_rng(seed)
    rgb = np.zeros((FULL_H, FULL_W, 3), np.float32)
    semantic = np.zeros((FULL_H, FULL_W), np.uint8)
    instance = np.zeros((FULL_H, FULL_W), np.int32)
    rgb[:110], semantic[:110] = (0.55, 0.7, 0.95), SKY
    rgb[60:130, :120], semantic[60:130, :120] = (0.6, 0.5, 0.4), BUILDING
    rgb[60:130, 280:], semantic[60:130, 280:] = (0.45, 0.45, 0.5), BUILDING
    rgb[130:], semantic[130:] = (0.3, 0.3, 0.32), ROAD
    rgb[135:256:12, 188:196], semantic[135:256:12, 188:196] = (0.95, 0.95, 0.9), MARKING
    rgb[150:185, 60:130], semantic[150:185, 60:130], instance[150:185, 60:130] = (0.1, 0.2, 0.7), CAR, 3
    rgb[170:200, 220:250], semantic[170:200, 220:250], instance[170:200, 220:250] = (0.9, 0.3, 0.1), ANOMALY, 8
    rgb += rng.normal(0, 0.02, rgb.shape).astype(np.float32)
    return np.clip(rgb, 0, 1), instance, semantic


def scene_frame(seed: int = 0, with_truth: bool = True) -> Frame:
    rgb, instance, semantic = driving_scene(seed)
    target = rgb[::2, ::2].copy()  # (128, 192, 3): the world model's plain resize
    inputs = {"frame": Message("drive", seed, arrays={"target": target})}
    if with_truth:
        inputs["truth"] = Message("drive", seed, arrays={"instance": instance, "semantic": semantic})
    return Frame("drive", seed, 0, inputs=inputs)


IMAGE_METHODS = ["felzenszwalb", "slic", "kmeans"]


@pytest.mark.parametrize("method", ["gt", *IMAGE_METHODS])
def test_output_contract(method):
    op = Segmenter({"method": method})
    for seed in (0, 1):
        out = op.process(scene_frame(seed))["masks"]
        masks = out.arrays["masks"]
        assert masks.dtype == bool and masks.ndim == 3 and masks.shape[1:] == (H, W)
        assert out.meta == {"method": method, "count": masks.shape[0]}
        assert masks.shape[0] >= 2 and masks.any(axis=(1, 2)).all()
        assert masks.sum(axis=0).max() == 1, "built-in methods tile the image: no pixel in two masks"


@pytest.mark.parametrize("method", IMAGE_METHODS)
def test_unsupervised_methods_need_no_truth_and_are_deterministic(method):
    op = Segmenter({"method": method})
    one = op.process(scene_frame(0, with_truth=False))["masks"].arrays["masks"]
    two = op.process(scene_frame(0, with_truth=False))["masks"].arrays["masks"]
    np.testing.assert_array_equal(one, two)


def test_unsupervised_methods_separate_the_anomaly_from_the_road():
    anomaly = resize_nearest(driving_scene()[1], (H, W)) == 8
    for method in IMAGE_METHODS:
        masks = Segmenter({"method": method}).process(scene_frame())["masks"].arrays["masks"]
        purity = (masks & anomaly).sum(axis=(1, 2)) / masks.sum(axis=(1, 2))
        covered = masks[purity >= 0.5].any(axis=0) & anomaly
        assert covered.sum() >= 0.8 * anomaly.sum(), method


def test_gt_masks_are_the_instance_ids_resized_nearest():
    frame = scene_frame()
    instance = resize_nearest(frame.inputs["truth"].arrays["instance"], (H, W))
    masks = Segmenter({"method": "gt", "options": {"stuff": False}}).process(frame)["masks"].arrays["masks"]
    expected = np.stack([instance == 3, instance == 8])  # largest first: the car, then the anomaly
    np.testing.assert_array_equal(masks, expected)


def test_gt_stuff_regions_tile_the_rest_by_semantic_class_and_connectivity():
    frame = scene_frame()
    instance = resize_nearest(frame.inputs["truth"].arrays["instance"], (H, W))
    semantic = resize_nearest(frame.inputs["truth"].arrays["semantic"], (H, W))
    masks = Segmenter({"method": "gt", "options": {"stuff_min_area": 1}}).process(frame)["masks"].arrays["masks"]
    np.testing.assert_array_equal(masks[:2], np.stack([instance == 3, instance == 8]))
    assert masks.sum(axis=0).max() == 1 and masks.any(axis=0).all()
    for mask in masks[2:]:
        assert len(np.unique(semantic[mask])) == 1 and (instance[mask] == 0).all()
        assert connected_regions(np.where(mask, 1, -1)).max() == 0  # one 4-connected region
    lane_marks = connected_regions(np.where(semantic == MARKING, 1, -1)).max() + 1
    assert sum(1 for m in masks[2:] if (semantic[m] == MARKING).all()) == lane_marks == 11


def test_labels_to_masks_drops_small_and_ignored_labels():
    labels = np.array([[0, 0, 1], [2, 2, 2]])
    masks = labels_to_masks(labels, min_area=2, ignore=0)
    np.testing.assert_array_equal(masks, [labels == 2])
    assert labels_to_masks(labels, min_area=9).shape == (0, 2, 3)


def test_gt_without_truth_and_bad_targets_are_refused():
    with pytest.raises(ValueError, match="input 'truth' lacks array 'instance'"):
        Segmenter({"method": "gt"}).process(scene_frame(with_truth=False))
    gray = Frame("drive", 0, 0, inputs={"frame": Message("drive", 0, arrays={"target": np.zeros((H, W))})})
    with pytest.raises(ValueError, match=r"expected \(h, w, 3\)"):
        Segmenter({"method": "slic"}).process(gray)
    with pytest.raises(ValidationError, match="unknown segmenter method 'watershed'"):
        Segmenter({"method": "watershed"})
    with pytest.raises(ValidationError, match="method 'slic' options: segments: Extra inputs"):
        Segmenter({"method": "slic", "options": {"segments": 10}})
    with pytest.raises(ValidationError, match="n_segments"):
        Segmenter({"method": "slic", "options": {"n_segments": 0}})


def test_sam_missing_checkpoint_fails_at_construction(tmp_path):
    missing = tmp_path / "nowhere" / "sam_vit_b.pth"
    with pytest.raises(FileNotFoundError, match=r"sam_vit_b\.pth.*option checkpoint"):
        Segmenter({"method": "sam", "options": {"checkpoint": str(missing)}})


def test_sam_relative_checkpoint_resolves_against_the_graph_folder(tmp_path):
    with pytest.raises(FileNotFoundError, match=str(tmp_path / "weights" / "sam.pth")):
        Segmenter({"method": "sam", "options": {"checkpoint": "weights/sam.pth"}}, Context(base_dir=tmp_path))


def test_sam_without_checkpoint_parameter_fails_at_construction():
    with pytest.raises(ValueError, match="needs option checkpoint"):
        Segmenter({"method": "sam"})


def test_sam_without_package_fails_at_construction(tmp_path, monkeypatch):
    checkpoint = tmp_path / "sam.pth"
    checkpoint.write_bytes(b"never read: the package is missing")
    monkeypatch.setitem(sys.modules, "segment_anything", None)  # import fails as if not installed
    with pytest.raises(ImportError, match=r"segment-anything.*sam_env\.sh"):
        Segmenter({"method": "sam", "options": {"checkpoint": str(checkpoint)}})


def test_switching_to_sam_with_a_missing_checkpoint_keeps_the_old_method(tmp_path):
    op = Segmenter({"method": "slic"})
    with pytest.raises(FileNotFoundError):
        op.update_params(
            Segmenter.validate_params({"method": "sam", "options": {"checkpoint": str(tmp_path / "x.pth")}})
        )
    assert op.params.method == "slic"
    assert op.process(scene_frame())["masks"].meta["method"] == "slic"


def test_kmeans_on_feature_net_features(tmp_path):
    torch = pytest.importorskip("torch")
    from umad_common.models.feature_net import FeatureNet, save_feature_net

    torch.set_num_threads(1)
    torch.manual_seed(0)
    weights = tmp_path / "features.safetensors"
    save_feature_net(FeatureNet(), weights)
    op = Segmenter({"method": "kmeans", "options": {"features": "feature_net", "feature_net": str(weights)}})
    masks = op.process(scene_frame())["masks"].arrays["masks"]
    assert masks.dtype == bool and masks.shape[1:] == (H, W) and masks.shape[0] >= 2
    assert masks.sum(axis=0).max() == 1


def test_kmeans_feature_net_file_is_checked_at_construction(tmp_path):
    with pytest.raises(ValueError, match="needs option feature_net"):
        Segmenter({"method": "kmeans", "options": {"features": "feature_net"}})
    with pytest.raises(ValueError, match="missing.json"):
        Segmenter(
            {
                "method": "kmeans",
                "options": {"features": "feature_net", "feature_net": str(tmp_path / "missing.safetensors")},
            }
        )


def test_quality_counts_anomaly_pixels_in_masks_at_least_half_anomaly():
    from umad_common.benchmarks.segmentation_quality import frame_quality

    anomaly = np.zeros((4, 6), np.uint8)
    anomaly[0, :3] = 1  # object A: 3 px
    anomaly[3, 4:] = 1  # object B: 2 px
    anomaly[1, 5] = 255  # ignored: counts in no mask's area
    masks = np.zeros((3, 4, 6), dtype=bool)
    masks[0, :2, :3] = True  # 3 of 6 px anomaly: exactly half -> covers A
    masks[1, 2:, 3:] = True  # 2 of 6 px anomaly: a third -> covers nothing
    masks[2, 1, 4:] = True  # 0 anomaly, one ignored pixel
    total, covered, best, normal_area, normal = frame_quality(masks, anomaly)
    assert (total, covered) == (5, 3)
    assert best == pytest.approx([3 / 6, 2 / 6])
    assert (normal_area, normal) == (3 * 6 + 4 * 6 + 1 * 1, 3 + 4 + 1)
    assert frame_quality(masks[:0], anomaly) == (5, 0, [0.0, 0.0], 0.0, 0.0)
    one_instance = np.where(anomaly == 1, 7, 0)  # A and B are parts of one object
    assert frame_quality(masks, anomaly, one_instance)[2] == pytest.approx([3 / 8])


def test_measure_segmenter_reports_refined_ap_when_frames_carry_a_fused_map():
    from umad_common.benchmarks.segmentation_quality import LabelledFrame, measure_segmenter

    rng = np.random.default_rng(5)
    frames = []
    for seed in (0, 1):
        rgb, instance, semantic = driving_scene(seed)
        anomaly = (instance == 8).astype(np.uint8)
        speckle = rng.random((H, W)).astype(np.float32) ** 4  # normal structure: sparse high errors
        fused = np.clip(speckle + 0.4 * resize_nearest(anomaly, (H, W)), 0, 1)
        frames.append(LabelledFrame("drive", seed, rgb[::2, ::2].copy(), anomaly, instance, semantic, fused))
    gt = measure_segmenter({"method": "gt", "options": {"stuff_min_area": 1}}, frames)  # every pixel in a mask
    assert gt.frames == 2 and gt.coverage == 1.0 and gt.best_iou == 1.0
    assert gt.refined_ap == 1.0 > gt.pixel_ap
    assert gt.refined_fpr95 == 0.0 < gt.pixel_fpr95  # the anomaly's mask alone scores above every normal pixel
    plain = [LabelledFrame(f.run, f.seq, f.target, f.anomaly, f.instance, f.semantic) for f in frames]
    without_maps = measure_segmenter({"method": "gt"}, plain)
    assert without_maps.refined_ap is None and without_maps.pixel_ap is None and without_maps.refined_fpr95 is None


def test_every_registered_method_has_a_name_schema_and_grid_over_its_own_options():
    for name, cls in SEGMENTERS.items():
        assert cls.name == name
        assert set(cls.tuning_grid) <= set(cls.Params.model_fields), name
        for field_name, field in cls.Params.model_fields.items():
            assert field.description, f"{name}.{field_name} lacks a description"


def test_a_users_segmenter_loads_by_import_path(tmp_path, monkeypatch):
    (tmp_path / "my_segmenters.py").write_text(
        textwrap.dedent(
            """
            import numpy as np
            from pydantic import BaseModel, ConfigDict, Field
            from umad_common.segmentation import SegmenterMethod

            class Halves(SegmenterMethod):
                class Params(BaseModel):
                    model_config = ConfigDict(extra="forbid")
                    row: int = Field(10, description="where the lower half starts")

                def __call__(self, image, frame):
                    top = np.zeros(image.shape[:2], bool)
                    top[: self.params.row] = True
                    return np.stack([top, ~top])
            """
        )
    )
    monkeypatch.syspath_prepend(tmp_path)
    out = Segmenter({"method": "my_segmenters:Halves", "options": {"row": 5}}).process(scene_frame())["masks"]
    masks = out.arrays["masks"]
    assert out.meta["method"] == "my_segmenters:Halves" and masks.shape == (2, H, W)
    assert masks[0, :5].all() and not masks[0, 5:].any()
    with pytest.raises(ValidationError, match="row"):
        Segmenter({"method": "my_segmenters:Halves", "options": {"row": "middle"}})
    with pytest.raises(ValidationError, match="expected a SegmenterMethod subclass"):
        Segmenter({"method": "my_segmenters:np"})
    with pytest.raises(ValidationError, match="cannot import module 'no_such_module'"):
        Segmenter({"method": "no_such_module:Thing"})


# -- geometry -------------------------------------------------------------------------------------

MOUNT = 1.8  # lidar and camera height (m), as in AnoVox
BOX = {"x": (10.0, 11.0), "y": (-0.5, 0.5), "z": (0.0, 1.0)}  # 1 m cube on the road, 10 m ahead (ground z = 0)


def box_on_a_plane() -> np.ndarray:
    """(N, 4) lidar cloud (x, -y, z, intensity) in the lidar frame: flat ground 1.8 m below the sensor
    every 0.2 m, and the front face of a box (x = 10 m, |y| <= 0.5 m, 1 m tall) every 5 cm."""
    gx, gy = np.meshgrid(np.arange(3.0, 40.0, 0.2), np.arange(-20.0, 20.0, 0.2), indexing="ij")
    ground = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, -MOUNT)], axis=1)
    ground = ground[~((ground[:, 0] >= BOX["x"][0]) & (np.abs(ground[:, 1]) <= 0.5))]  # hidden behind the box
    fy, fz = np.meshgrid(np.arange(-0.5, 0.501, 0.05), np.arange(0.0, 1.001, 0.05), indexing="ij")
    face = np.stack([np.full(fy.size, BOX["x"][0]), fy.ravel(), fz.ravel() - MOUNT], axis=1)
    cloud = np.concatenate([ground, face])
    return np.concatenate([cloud, np.ones((len(cloud), 1))], axis=1).astype(np.float32)


def box_pixels(shape=(H, W), above=0.0) -> np.ndarray:
    """The box's front face in an AnoVox camera (768x512, FOV 90, same mount) resized to `shape`,
    from its height `above` the ground up: focal 96 px at width 192."""
    h, w = shape
    focal = w / 2  # FOV 90
    x = BOX["x"][0]
    col = lambda y: w / 2 + focal * -y / x  # noqa: E731
    row = lambda z: h / 2 - focal * (z - MOUNT) / x  # noqa: E731
    mask = np.zeros(shape, bool)
    mask[
        int(np.floor(row(BOX["z"][1]))) : int(np.floor(row(above))) + 1,
        int(np.floor(col(0.5))) : int(np.floor(col(-0.5))) + 1,
    ] = True
    return mask


def lidar_frame(points: np.ndarray, sensors: dict | None = None, image: np.ndarray | None = None) -> Frame:
    target = np.full((H, W, 3), 0.5, np.float32) if image is None else image
    inputs = {
        "frame": Message("drive", 0, arrays={"target": target}),
        "lidar": Message("drive", 0, meta={"sensors": sensors} if sensors else {}, arrays={"points": points}),
    }
    return Frame("drive", 0, 0, inputs=inputs)


ANOVOX_RIG = {"calibration": "options", "rest": ""}  # the option defaults are AnoVox's camera and mounts


def test_geometry_box_above_a_ground_plane_is_one_mask_at_the_right_pixels():
    masks = Segmenter({"method": "geometry", "options": ANOVOX_RIG}).process(lidar_frame(box_on_a_plane()))
    masks = masks["masks"].arrays["masks"]
    assert masks.shape == (1, H, W), "one object: the ground is removed, nothing else is above it"
    expected = box_pixels(above=0.25)  # points less than 0.2 m above the ground are ground
    inside = box_pixels()
    assert (masks[0] & expected).sum() >= 0.9 * expected.sum()
    assert not (masks[0] & ~inside).any(), "nothing outside the box's face"


def test_geometry_tiles_the_frame_with_the_rest_method_and_grows_objects_into_its_segments():
    image = np.full((H, W, 3), 0.3, np.float32)
    image[box_pixels()] = (0.9, 0.2, 0.1)  # the box's colour: its own image segment, down to the road
    options = {**ANOVOX_RIG, "rest": "felzenszwalb"}
    masks = Segmenter({"method": "geometry", "options": options}).process(lidar_frame(box_on_a_plane(), image=image))
    masks = masks["masks"].arrays["masks"]
    assert masks.sum(axis=0).min() == masks.sum(axis=0).max() == 1, "every pixel in exactly one mask"
    np.testing.assert_array_equal(masks[0], box_pixels()), "the object's mask is its whole image segment"


def test_an_object_region_grown_in_a_window_around_its_hits_is_the_whole_images_answer():
    from scipy import ndimage

    from umad_common.segmentation.geometry import CROSS, grown_box, hit_region

    rng = np.random.default_rng(0)
    for _ in range(300):  # scattered hits and a blob anywhere, often touching the image's border
        h, w = rng.integers(3, 24, 2)
        hits = rng.random((h, w)) < rng.uniform(0.02, 0.5)
        top, left = rng.integers(0, h), rng.integers(0, w)
        hits[top : top + rng.integers(1, 8), left : left + rng.integers(1, 8)] = True
        close_px = int(rng.integers(0, 4))
        whole = hits
        if close_px:
            whole = ndimage.binary_closing(hits, CROSS, iterations=close_px, border_value=0)
        whole = ndimage.binary_fill_holes(whole)
        window = grown_box(ndimage.find_objects(hits.astype(int))[0], close_px + 1, (h, w))
        region = np.zeros((h, w), bool)
        region[window] = hit_region(hits[window], close_px)
        assert np.array_equal(region, whole)


def test_snap_grows_an_object_into_pixels_of_its_colour_and_no_further():
    from umad_common.segmentation.geometry import snap_to_colour

    image = np.full((12, 12, 3), 0.4, np.float32)
    image[3:8, 3:8] = (0.9, 0.3, 0.1)  # the object, a 5 x 5 block; its lidar region is the inner 3 x 3
    image[0:2, 0:2] = (0.9, 0.3, 0.1)  # the same colour, out of reach
    owner = np.full((12, 12), -1, np.int64)
    owner[4:7, 4:7] = 0
    owner[8, 3:8] = 1  # another object below it: never taken
    for reach in (1, 2, 3):
        grown = owner.copy()
        snap_to_colour(grown, image, 2, reach)
        expected = np.zeros((12, 12), bool)
        expected[3:8, 3:8] = True
        np.testing.assert_array_equal(grown == 0, expected)
        np.testing.assert_array_equal(grown == 1, owner == 1)
    dark = image.copy()
    dark[3:8, 3:8] = 0.4  # the pixels around the region look like the background: nothing joins
    dark[4:7, 4:7] = (0.9, 0.3, 0.1)
    grown = owner.copy()
    snap_to_colour(grown, dark, 2, 2)
    np.testing.assert_array_equal(grown, owner)


def test_geometry_snaps_by_default_adding_the_objects_rim_that_its_hits_miss():
    image = np.full((H, W, 3), 0.3, np.float32)
    face = box_pixels()
    image[ndimage_dilate(face)] = (0.9, 0.2, 0.1)  # the object drawn a pixel wider than the lidar sees it
    options = {**ANOVOX_RIG, "snap_px": 0}
    plain = Segmenter({"method": "geometry", "options": options}).process(lidar_frame(box_on_a_plane(), image=image))
    snapped = Segmenter({"method": "geometry", "options": ANOVOX_RIG}).process(
        lidar_frame(box_on_a_plane(), image=image)
    )
    plain, snapped = plain["masks"].arrays["masks"][0], snapped["masks"].arrays["masks"][0]
    red = ndimage_dilate(face)
    assert (snapped & red).sum() > (plain & red).sum(), "the rim joins"
    assert not (snapped & ~red).any(), "nothing of the background's colour joins"


def ndimage_dilate(mask: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    return ndimage.binary_dilation(mask, ndimage.generate_binary_structure(2, 1))


def test_geometry_reads_the_camera_and_mounts_from_the_sensor_setup(tmp_path):
    from umad_common.datasets.anovox import read_sensor_setup
    from umad_common.datasets.synthetic.generator import sensor_setup
    from umad_common.datasets.synthetic.render import CameraSpec, LidarSpec

    (tmp_path / "sensor_setup.json").write_text(json.dumps(sensor_setup(CameraSpec(384, 256), LidarSpec())))
    sensors = read_sensor_setup(tmp_path / "sensor_setup.json")
    assert sensors["camera"] == {
        "width": 384,
        "height": 256,
        "fov": 90.0,
        "location": [0, 0, 1.8],
        "rotation": [0, 0, 0],
    }
    op = Segmenter({"method": "geometry", "options": {"rest": "", "calibration": "data"}})
    level = op.process(lidar_frame(box_on_a_plane(), sensors))["masks"].arrays["masks"]
    assert level.shape == (1, H, W) and (level[0] & box_pixels(above=0.25)).sum() >= 0.9 * box_pixels(above=0.25).sum()
    sensors["lidar"]["location"] = [0, 0, 2.8]  # the lidar 1 m above the camera: the box appears 1 m higher
    masks = op.process(lidar_frame(box_on_a_plane(), sensors))["masks"].arrays["masks"]
    assert (
        masks[0].any() and np.flatnonzero(masks[0].any(axis=1)).max() < np.flatnonzero(box_pixels().any(axis=1)).min()
    )
    with pytest.raises(ValueError, match="calibration: options or auto"):
        op.process(lidar_frame(box_on_a_plane()))  # no `sensors` meta
    auto = Segmenter({"method": "geometry", "options": {"rest": ""}})  # the default: data, else the options
    np.testing.assert_array_equal(auto.process(lidar_frame(box_on_a_plane(), sensors))["masks"].arrays["masks"], masks)
    no_setup = auto.process(lidar_frame(box_on_a_plane()))["masks"].arrays["masks"]  # AnoVox's camera, same FOV
    np.testing.assert_array_equal(no_setup, level)
    sensors["camera"]["rotation"] = [0, 10, 0]
    with pytest.raises(ValueError, match="camera rotation"):
        op.process(lidar_frame(box_on_a_plane(), sensors))


def test_geometry_without_lidar_is_refused_or_falls_back_to_the_rest_method():
    empty = np.zeros((0, 4), np.float32)
    with pytest.raises(ValueError, match="got no lidar points.*no_lidar: rest"):
        Segmenter({"method": "geometry", "options": {"calibration": "options"}}).process(lidar_frame(empty))
    fallback = Segmenter({"method": "geometry", "options": {"no_lidar": "rest", "rest": "slic"}})
    frame = lidar_frame(empty, image=scene_frame().inputs["frame"].arrays["target"])
    slic = Segmenter({"method": "slic"}).process(frame)["masks"].arrays["masks"]
    np.testing.assert_array_equal(fallback.process(frame)["masks"].arrays["masks"], slic)
    no_port = scene_frame(with_truth=False)
    with pytest.raises(ValueError, match="input 'lidar' lacks array 'points'"):
        Segmenter({"method": "geometry"}).process(no_port)
    with pytest.raises(ValidationError, match="would nest geometry"):
        Segmenter({"method": "geometry", "options": {"rest": "geometry"}})


def test_geometry_finds_a_rendered_anomaly_of_the_built_in_world():
    """The renderer's own camera and lidar (independent of the projection code): the anomaly's
    instance pixels lie mostly in one geometry mask that is mostly anomaly."""
    from umad_common.datasets.anovox import ANOMALY_TAGS
    from umad_common.datasets.synthetic.scenario import SyntheticScenario

    scenario = SyntheticScenario(seed=3, frames=40, anomaly_category="home", weather="clear_noon")
    sensors = {
        "camera": {"width": 384, "height": 256, "fov": 90.0, "location": [0, 0, 1.8], "rotation": [0, 0, 0]},
        "lidar": {"location": [0, 0, 1.8], "rotation": [0, 0, 0]},
    }
    op = Segmenter({"method": "geometry", "options": {"rest": ""}})
    best = 0.0
    for i in (20, 30, 39):
        frame = scenario.render(i)
        anomaly = np.isin(resize_nearest(frame.camera.semantic, (H, W)), ANOMALY_TAGS)
        if anomaly.sum() < 20:
            continue
        image = frame.camera.rgb[::2, ::2].astype(np.float32) / 255
        masks = op.process(lidar_frame(frame.lidar, sensors, image))["masks"].arrays["masks"]
        iou = (masks & anomaly).sum(axis=(1, 2)) / (masks | anomaly).sum(axis=(1, 2))
        best = max(best, float(iou.max()))
    assert best >= 0.5


def test_bench_takes_methods_and_grids_from_the_registry():
    from umad_common.benchmarks.segmenters import VALIDATION_SEED, configurations

    assert VALIDATION_SEED not in (0, 1), "neither the training nor the evaluation seed"
    assert configurations(["geometry", "slic"], tune=False) == [
        {"method": "geometry", "options": {}},
        {"method": "slic", "options": {}},
    ]
    grid = SEGMENTERS["felzenszwalb"].tuning_grid
    tuned = configurations(["felzenszwalb"], tune=True)
    assert len(tuned) == len(grid["scale"]) * len(grid["sigma"])
    defaults = SEGMENTERS["felzenszwalb"].Params()
    assert {"scale": defaults.scale, "sigma": defaults.sigma} in [c["options"] for c in tuned], "default in its grid"


def test_segmenter_on_the_camera_gives_the_masks_it_gives_on_the_world_models_target():
    """Wired to the camera, the segmenter resizes the image as the world model does (area averaging to
    `image_size`), so its masks are those of the target the world model would publish; exactly one
    image input must be wired."""
    from umad_common.models.world_model import WorldModelConfig, resize_rgb

    rgb = np.random.default_rng(5).integers(0, 256, (256, 384, 3), dtype=np.uint8)
    rgb[60:140, 100:220] = (250, 20, 20)
    target = resize_rgb(rgb, WorldModelConfig()).astype(np.float32) / 255.0
    on_target = Segmenter({"method": "slic"}).process(
        Frame("run", 0, 0, inputs={"frame": Message("run", 0, arrays={"target": target})})
    )["masks"]
    on_camera = Segmenter({"method": "slic", "image_size": (192, 128)}).process(
        Frame("run", 0, 0, inputs={"camera": Message("run", 0, arrays={"rgb": rgb})})
    )["masks"]
    assert on_camera.arrays["masks"].shape[1:] == (128, 192)
    np.testing.assert_array_equal(on_camera.arrays["masks"], on_target.arrays["masks"])
    params = Segmenter.Params(method="slic")
    assert Segmenter.wiring_problems(params, {"camera"}) == []
    for wired in (set(), {"frame", "camera"}):
        (problem,) = Segmenter.wiring_problems(params, wired)
        assert "exactly one image input" in problem


def sparse_points(x: float, count: int) -> np.ndarray:
    """`count` lidar hits 0.3 m apart up a thin object x m ahead (0.3-0.9 m above the ground): what a
    64-channel lidar returns from a small obstacle at 20-40 m."""
    z = 0.3 + 0.3 * np.arange(count) - MOUNT
    return np.column_stack([np.full(count, x), np.zeros(count), z, np.ones(count)]).astype(np.float32)


def ground_only() -> np.ndarray:
    cloud = box_on_a_plane()
    return cloud[cloud[:, 2] < -MOUNT + 0.01]


@pytest.mark.parametrize(
    ("x", "count", "near_range", "objects"),
    [
        (30.0, 3, 0.0, 0),  # every point counts once: 3 hits < 4, the far obstacle is no object
        (30.0, 3, 10.0, 1),  # at 30 m each hit counts as 2 (9, capped at 4 / 2): an object
        (30.0, 1, 10.0, 0),  # one stray hit is never an object, however far (far_min_points 2)
        (8.0, 3, 10.0, 0),  # within near_range the count is as before
    ],
)
def test_geometry_near_range_lets_a_far_obstacle_with_few_lidar_hits_be_an_object(x, count, near_range, objects):
    cloud = np.concatenate([ground_only(), sparse_points(x, count)])
    options = {**ANOVOX_RIG, "near_range": near_range}
    masks = Segmenter({"method": "geometry", "options": options}).process(lidar_frame(cloud))["masks"].arrays["masks"]
    assert masks.shape[0] == objects
