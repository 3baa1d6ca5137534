"""The `geometry` segmenter: objects from the lidar, cut out of the image where the lidar sees them.

Per frame:

1. project the lidar points into the segmenter's image with the camera's field of view and the
   camera and lidar mounts (the scenario's sensor_setup.json, which the replayer sends as the lidar
   message's meta `sensors`; or the options, whose defaults are AnoVox's);
2. fit the ground plane with RANSAC and drop the points less than `ground_height` above it;
3. cluster the remaining points with DBSCAN: one cluster per object (with `near_range`, a far point
   counts as several, as a far object returns fewer hits);
4. grow each cluster into its image region: the pixels its points hit (closed, holes filled), plus
   every segment of the `rest` method whose lidar-hit pixels are mostly that cluster's; with
   `snap_px`, then up to that many pixels further where the image's colour says object, not background;
5. the `rest` method's segments, less the objects, cover everything else, so the masks tile the
   frame: geometry where the lidar sees an object, image segments elsewhere (the combination).

No depth camera, no labels. Camera and lidar axes follow CARLA (x forward, y right, z up, metres);
AnoVox clouds store (x, -y, z, intensity) in the lidar's frame.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from scipy import ndimage

from umad_common.dataflow import Context, Frame, input_array
from umad_common.datasets.sensor_rig import SensorRig, SensorSetupError, Triplet
from umad_common.segmentation.base import (
    TUNED,
    SegmenterInputError,
    SegmenterMethod,
    masks_to_labels,
    sklearn_cluster,
)
from umad_common.segmentation.registry import UnknownSegmenterError, segmenter_class

CROSS = ndimage.generate_binary_structure(2, 1)  # 4-connectivity
SQUARE = ndimage.generate_binary_structure(2, 2)  # 8-connectivity
SNAP_MIN_CONTRAST = 0.05  # snap_px: mean colours (RGB in [0, 1]) nearer than this do not tell object from background


def fit_ground(xyz: np.ndarray, iterations: int, tolerance: float, seed: int = 0) -> np.ndarray:
    """RANSAC plane (a, b, c, d) with a x + b y + c z + d = 0, unit normal pointing up (c > 0), among
    near-horizontal planes (normal within 30 degrees of vertical), refined by least squares on its
    inliers. With fewer than 3 points: the plane z = min(z) (or z = 0 without points)."""
    if len(xyz) < 3:
        return np.array([0.0, 0.0, 1.0, -(xyz[:, 2].min() if len(xyz) else 0.0)])
    rng = np.random.default_rng(seed)
    samples = xyz[rng.integers(0, len(xyz), size=(iterations, 3))]  # (I, 3, 3)
    normals = np.cross(samples[:, 1] - samples[:, 0], samples[:, 2] - samples[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    normals = normals / np.maximum(norms, 1e-9)[:, None] * np.sign(normals[:, 2:3] + 1e-12)
    offsets = -np.einsum("ij,ij->i", normals, samples[:, 0])
    valid = (norms > 1e-9) & (normals[:, 2] > np.cos(np.radians(30)))
    if not valid.any():
        return np.array([0.0, 0.0, 1.0, -np.percentile(xyz[:, 2], 5)])
    inliers = np.abs(xyz @ normals[valid].T + offsets[valid]) < tolerance  # (N, I')
    best = int(inliers.sum(axis=0).argmax())
    support = xyz[inliers[:, best]]
    if len(support) >= 3:  # least squares z = p x + q y + r on the inliers
        design = np.column_stack([support[:, 0], support[:, 1], np.ones(len(support))])
        p, q, r = np.linalg.lstsq(design, support[:, 2], rcond=None)[0]
        plane = np.array([-p, -q, 1.0, -r])
        return plane / np.linalg.norm(plane[:3])
    return np.append(normals[valid][best], offsets[valid][best])


class Geometry(SegmenterMethod):
    """Lidar objects (ground removed, DBSCAN clusters) grown into image regions, plus the `rest`
    method's segments elsewhere."""

    name = "geometry"
    needs = ("lidar",)
    tuning_grid = {
        "cluster_eps": [0.7, 1.0],
        "share": [0.3, 0.5],
        "ground_height": [0.1, 0.2],
        "rest": ["felzenszwalb", "slic"],
    }

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")

        calibration: Literal["auto", "data", "options"] = Field(
            "auto",
            description="data: camera and mounts from the lidar message's meta `sensors` (the scenario's "
            "sensor_setup.json; a frame without it is refused); options: the fields below; auto: data when the "
            "frame has it, else the options, with a warning once per run",
        )
        image_size: tuple[int, int] = Field(
            (768, 512), description="calibration options: camera width, height (px) before any resize (AnoVox)"
        )
        fov: float = Field(90.0, gt=0, lt=180, description="calibration options: horizontal FOV (deg) (AnoVox)")
        camera_location: Triplet = Field(
            (0.0, 0.0, 1.8), description="calibration options: camera mount x, y, z (m, CARLA axes) (AnoVox)"
        )
        lidar_location: Triplet = Field(
            (0.0, 0.0, 1.8), description="calibration options: lidar mount x, y, z (m, CARLA axes) (AnoVox)"
        )
        min_range: float = Field(2.5, ge=0, description="ignore points closer than this (m): the ego vehicle")
        max_range: float = Field(80.0, gt=0, description="ignore points farther than this (m)")
        ground_tolerance: float = Field(0.1, gt=0, description="RANSAC: inlier distance to the ground plane (m)")
        ground_iterations: int = Field(64, ge=1, description="RANSAC: candidate planes")
        ground_height: float = Field(
            0.1, ge=0, description=f"points less than this above the ground are ground (m); {TUNED}"
        )
        cluster_eps: float = Field(0.7, gt=0, description=f"DBSCAN: neighbourhood radius (m); {TUNED}")
        cluster_min_points: int = Field(4, ge=1, description="DBSCAN: points in a neighbourhood to seed a cluster")
        near_range: float = Field(
            0.0,
            ge=0,
            description="beyond this range (m) a point counts as (range / near_range)^2 points toward "
            "cluster_min_points, as the lidar's hits on an object thin out with the square of its range; 0: every "
            "point counts once",
        )
        far_min_points: int = Field(
            2, ge=1, description="with near_range: the fewest points that seed a cluster however far (caps the count)"
        )
        share: float = Field(
            0.5,
            gt=0,
            le=1,
            description=f"a rest segment joins an object when this share of its lidar-hit pixels is it; {TUNED}",
        )
        close_px: int = Field(1, ge=0, description="close each object's hit pixels with this radius (px) first")
        snap_px: int = Field(
            1,
            ge=0,
            description="grow each object by up to this many pixels (ours) into the free pixels around it whose colour "
            "is nearer the object's mean colour than the mean colour just beyond (the lidar's rays land about a pixel "
            "apart at model resolution, so an object reaches past its outermost hits); 0: off. 1 chosen on "
            "validation seeds 2 and 31 (`umad eval --data`, refined AP and FPR95; docs/experiments.md)",
        )
        rest: str = Field(
            "slic",
            description="the method whose segments cover the rest of the frame and grow the objects (a registered "
            f"name or `package.module:Class`; its masks are flattened to a tiling); empty: object masks only; {TUNED}",
        )
        rest_options: dict[str, Any] = Field(default_factory=dict, description="the rest method's options")
        no_lidar: Literal["error", "rest"] = Field(
            "error",
            description="a frame with no lidar points: error (the frame is refused, naming it), or rest (the rest "
            "method's segments alone)",
        )

        @model_validator(mode="after")
        def _rest_is_an_image_method(self) -> Geometry.Params:
            rest_class(self.rest, self.rest_options)
            return self

    def __init__(self, params: BaseModel, context: Context):
        super().__init__(params, context)
        p = self.params
        cls = rest_class(p.rest, p.rest_options)
        self.rest = cls.from_options(p.rest_options, context) if cls else None
        self.options_rig = SensorRig(p.image_size[0], p.image_size[1], p.fov, p.camera_location, p.lidar_location)
        self.assumed_runs: set[str] = set()  # auto calibration: runs already warned about
        self.dbscan = sklearn_cluster().DBSCAN

    @classmethod
    def required_inputs(cls, params: BaseModel) -> set[str]:
        rest = rest_class(params.rest, params.rest_options)
        if rest is None:
            return set(cls.needs)
        return set(cls.needs) | rest.required_inputs(rest.Params.model_validate(params.rest_options))

    def __call__(self, image: np.ndarray, frame: Frame) -> np.ndarray:
        p = self.params
        shape = image.shape[:2]
        points = np.asarray(input_array(frame, "lidar", "points", f"segmenter method {self.name!r}"), np.float64)
        rest = self.rest(image, frame) if self.rest is not None else np.zeros((0, *shape), bool)
        if len(points) == 0:
            if p.no_lidar == "error":
                raise SegmenterInputError(
                    f"segmenter {frame.frame_id}: method 'geometry' got no lidar points (a drive without lidar?); "
                    "expected a (N, 4) cloud on input 'lidar', or option no_lidar: rest"
                )
            return rest
        rig = self.rig_of(frame)
        objects = self.objects(points, rig, shape, rest, image)
        rest = rest & ~objects.any(axis=0)
        return np.concatenate([objects, rest[rest.any(axis=(1, 2))]], axis=0)

    def rig_of(self, frame: Frame) -> SensorRig:
        """The camera and mounts for this frame, as the `calibration` option says."""
        p = self.params
        sensors = frame.inputs["lidar"].meta.get("sensors")
        if p.calibration == "options" or (p.calibration == "auto" and not sensors):
            if p.calibration == "auto" and frame.run not in self.assumed_runs:
                self.assumed_runs.add(frame.run)
                self.context.log.warning(
                    "segmenter %s: the lidar carries no sensor setup; geometry projects with the options' camera %s",
                    frame.frame_id,
                    self.options_rig,
                )
            return self.options_rig
        if not sensors:
            raise SegmenterInputError(
                f"segmenter {frame.frame_id}: method 'geometry' with calibration 'data' needs the lidar message's meta "
                "`sensors` (the replayer sends the scenario's sensor_setup.json; the benchmark layout has none); "
                "set option calibration: options or auto (defaults: AnoVox's 768x512, FOV 90, mounts (0, 0, 1.8))"
            )
        try:
            return SensorRig.from_sensors(sensors, f"segmenter {frame.frame_id}")
        except SensorSetupError as exc:
            raise SegmenterInputError(str(exc)) from None

    def objects(
        self, points: np.ndarray, rig: SensorRig, shape: tuple[int, int], rest: np.ndarray, image: np.ndarray
    ) -> np.ndarray:
        """(K, h, w) bool, one mask per lidar object seen in `image`, nearer objects on top."""
        p = self.params
        h, w = shape
        rows, cols, depth = rig.project(points[:, :3], shape)
        distance = np.hypot(points[:, 0], points[:, 1])
        seen = (depth > 0) & (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        seen &= (distance >= p.min_range) & (distance <= p.max_range)
        xyz = points[seen, :3] * (1.0, -1.0, 1.0)  # CARLA axes, lidar frame
        rows, cols, depth = rows[seen], cols[seen], depth[seen]
        plane = fit_ground(xyz, p.ground_iterations, p.ground_tolerance)
        above = xyz @ plane[:3] + plane[3] >= p.ground_height
        labels = np.full(len(xyz), -2, np.int64)  # -2 ground, -1 unclustered, >= 0 object
        weight = self.point_weights(distance[seen][above])  # None: every point counts once
        if (above.sum() if weight is None else weight.sum()) >= p.cluster_min_points:
            dbscan = self.dbscan(eps=p.cluster_eps, min_samples=p.cluster_min_points, algorithm="ball_tree")
            labels[above] = dbscan.fit_predict(xyz[above], sample_weight=weight)  # the ball tree finds the same
            #   neighbours as the default k-d tree in less CPU on these dense clouds (docs/experiments.md)
        else:
            labels[above] = -1
        count = int(labels.max()) + 1
        if count == 0:
            return np.zeros((0, h, w), bool)
        hit = np.full(shape, -3, np.int64)  # the nearest point's label per pixel; -3 no point
        order = np.lexsort((depth, rows * w + cols))
        pixel = rows[order] * w + cols[order]
        first = np.r_[True, pixel[1:] != pixel[:-1]]
        hit.reshape(-1)[pixel[first]] = labels[order][first]
        owner = np.full(shape, -1, np.int64)
        rest_labels = masks_to_labels(rest) if len(rest) else np.full(shape, -1, np.int64)
        joined = self._segments_joining(hit, rest_labels, count)
        segment_object = np.append(joined, -1)[rest_labels]  # (h, w) the object each pixel's segment joins, -1 none
        hit_boxes = ndimage.find_objects(hit + 3, max_label=count + 2)[2:]  # [k]: bounding box of object k's hits
        median_depth = [np.median(depth[labels == k]) for k in range(count)]
        for k in np.argsort(median_depth)[::-1]:  # far first: nearer objects overwrite
            if hit_boxes[k] is not None:
                window = grown_box(hit_boxes[k], p.close_px + 1, shape)
                owner[window][hit_region(hit[window] == k, p.close_px)] = k
            owner[segment_object == k] = k
        if p.snap_px:
            snap_to_colour(owner, image, count, p.snap_px)
        ids, sizes = np.unique(owner[owner >= 0], return_counts=True)
        ids = ids[np.argsort(-sizes, kind="stable")]
        return owner[None] == ids[:, None, None]

    def point_weights(self, distance: np.ndarray) -> np.ndarray | None:
        """What each point counts toward `cluster_min_points` at its range `distance` (m): 1 within
        `near_range`, (distance / near_range)^2 beyond, at most cluster_min_points / far_min_points;
        None without `near_range` (DBSCAN then counts points, without a per-point weighted sum)."""
        p = self.params
        if p.near_range <= 0:
            return None
        cap = max(p.cluster_min_points / p.far_min_points, 1.0)
        return np.clip((distance / p.near_range) ** 2, 1.0, cap)

    def _segments_joining(self, hit: np.ndarray, rest_labels: np.ndarray, count: int) -> np.ndarray:
        """Per rest segment, the object it joins (-1 none): the one holding at least `share` of the
        segment's lidar-hit pixels (ground and unclustered hits count against it)."""
        segments = int(rest_labels.max()) + 1
        if segments == 0:
            return np.zeros(0, np.int64)
        valid = (hit > -3) & (rest_labels >= 0)
        hits_per_segment = np.bincount(rest_labels[valid], minlength=segments)
        on_object = valid & (hit >= 0)
        votes = np.zeros((segments, count), np.int64)
        np.add.at(votes, (rest_labels[on_object], hit[on_object]), 1)
        best = votes.argmax(axis=1)
        enough = votes[np.arange(segments), best] >= self.params.share * np.maximum(hits_per_segment, 1)
        return np.where(enough & (hits_per_segment > 0), best, -1)


def grown_box(box: tuple[slice, slice], margin: int, shape: tuple[int, int]) -> tuple[slice, slice]:
    """The (rows, cols) slices of `box` grown by `margin` pixels on every side, within an image of `shape`."""
    return tuple(slice(max(s.start - margin, 0), min(s.stop + margin, n)) for s, n in zip(box, shape, strict=True))


def hit_region(hits: np.ndarray, close_px: int) -> np.ndarray:
    """The region an object's hit pixels (h, w) bool make: closed with radius `close_px` (4-connected,
    nothing outside the image), holes filled. Given a window around the hits grown by close_px + 1 it
    is the whole image's answer cut to the window: the closing reaches close_px beyond the hits, and
    the ring left around it is background that reaches the image's border."""
    if close_px:
        hits = ndimage.binary_closing(hits, CROSS, iterations=close_px, border_value=0)
    return ndimage.binary_fill_holes(hits)


def snap_to_colour(owner: np.ndarray, image: np.ndarray, count: int, reach: int) -> None:
    """Grow the objects of `owner` ((h, w) object index, -1 free; changed in place) a pixel at a time
    (8-connected), up to `reach` pixels, into free pixels whose colour in `image` (h, w, 3) is nearer
    the object's mean colour than its background's: the free pixels 1-2 pixels beyond that reach
    whose nearest object it is. An object whose mean colour is within SNAP_MIN_CONTRAST of its
    background's stays as it is; a pixel next to several objects joins, of the highest- and the
    lowest-index one, the one nearer its colour."""
    free = owner == -1
    if free.all() or not free.any():
        return
    colours = image.reshape(-1, image.shape[-1]).astype(np.float64)
    distance, (rows, cols) = ndimage.distance_transform_cdt(free, metric="chessboard", return_indices=True)
    nearest = owner[rows, cols]  # the nearest object of every pixel
    background = (free & (distance > reach) & (distance <= reach + 2)).reshape(-1)

    def mean_colours(pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        labels = nearest.reshape(-1)[pixels]
        counts = np.bincount(labels, minlength=count)
        sums = np.stack([np.bincount(labels, c, minlength=count) for c in colours[pixels].T], axis=1)
        return sums / np.maximum(counts, 1)[:, None], counts

    object_colour, _ = mean_colours(owner.reshape(-1) >= 0)
    background_colour, in_background = mean_colours(background)
    distinct = (in_background > 0) & (np.linalg.norm(object_colour - background_colour, axis=1) >= SNAP_MIN_CONTRAST)
    for _ in range(reach):
        free_pixels = np.flatnonzero(owner == -1)
        pixel = colours[free_pixels]
        best_distance = np.full(len(free_pixels), np.inf)
        best_object = np.full(len(free_pixels), -1)
        as_high = np.where(owner >= 0, owner, count)  # free pixels never win the minimum
        for neighbour in (
            ndimage.grey_dilation(owner, footprint=SQUARE, mode="constant", cval=-1),  # highest adjacent index
            ndimage.grey_erosion(as_high, footprint=SQUARE, mode="constant", cval=count),  # lowest
        ):
            k = neighbour.reshape(-1)[free_pixels]
            adjacent = (k >= 0) & (k < count)
            k = np.where(adjacent, k, 0)
            to_object = np.square(pixel - object_colour[k]).sum(axis=1)
            joins = adjacent & distinct[k] & (to_object < np.square(pixel - background_colour[k]).sum(axis=1))
            better = joins & (to_object < best_distance)
            best_distance[better], best_object[better] = to_object[better], k[better]
        if (best_object < 0).all():
            break
        owner.reshape(-1)[free_pixels[best_object >= 0]] = best_object[best_object >= 0]


def rest_class(name: str, options: dict[str, Any]) -> type[SegmenterMethod] | None:
    """The method that covers the rest of the frame (None for an empty name), its options checked;
    not geometry itself."""
    if not name:
        return None
    try:
        cls = segmenter_class(name)
    except UnknownSegmenterError as exc:
        raise ValueError(f"rest: {exc}") from None
    if issubclass(cls, Geometry):
        raise ValueError(f"rest method {name!r} would nest geometry; use an image method")
    try:
        cls.Params.model_validate(options)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise ValueError(f"rest_options for {name!r}: {problems}") from None
    return cls
