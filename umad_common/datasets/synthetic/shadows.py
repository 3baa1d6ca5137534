"""The sun's cast shadows on the ground, as a shadow map rasterised in the ground plane.

Every primitive is convex and stands above the ground, so a ground point lies in a primitive's
shadow exactly when the ray from it toward the sun meets that primitive, that is when the point
lies inside the primitive projected along the sun onto the ground: a convex polygon, the hull of
the projected outline. Filling those polygons into a raster around the camera answers the ray cast
of every ground pixel at once, for a few milliseconds a frame. The penumbra widens with the
distance from the ground to the occluder, as the sun's disc does: each point blends the raster's
sharp edge with a blurred one by its occluder's distance.
"""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np

from umad_common.datasets.synthetic.world import KIND_BOX, KIND_CONE, KIND_CYLINDER, KIND_ELLIPSOID, PrimSet

MAP_CELL_M = 0.1  # side of one shadow-map cell on the ground
MAP_AHEAD_M = (-10.0, 100.0)  # the map spans this far behind and ahead of the camera...
MAP_SIDE_M = 60.0  # ...and this far to either side of it (the camera's 90 degree view fits inside)
FADE_FROM_M = 85.0  # shadows fade out from here to the map's far edge, so the edge draws no line
PENUMBRA_FAR_SIGMA_M = 0.45  # blur of a shadow cast by an occluder PENUMBRA_FAR_M away (a nearer one: sharper)
PENUMBRA_FAR_M = 45.0
MAP_ROWS = int(round(2 * MAP_SIDE_M / MAP_CELL_M))  # left to right of the camera
MAP_COLS = int(round((MAP_AHEAD_M[1] - MAP_AHEAD_M[0]) / MAP_CELL_M))  # behind to ahead of it
COARSE = 4  # the soft shadow and the occluder distance are kept at MAP_CELL_M * COARSE
MIN_SUN_HEIGHT = 0.05  # sine of the lowest sun elevation that casts shadows (about 3 degrees)
_SUBPIXEL_BITS = 4  # cv2.fillConvexPoly's fixed-point precision


@cache
def unit_outline(kind: int) -> np.ndarray:
    """(S, 3) points of a unit primitive whose convex hull, projected along any direction, is the
    primitive's projected silhouette (exact for boxes, cylinders and cones; 96 points of the sphere)."""
    if kind == KIND_BOX:
        return np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    angle = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    circle = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    if kind == KIND_CYLINDER:
        return np.concatenate([np.c_[circle, np.full(32, z)] for z in (-1.0, 1.0)])
    if kind == KIND_CONE:
        return np.concatenate([np.c_[circle, np.full(32, -1.0)], [[0.0, 0.0, 1.0]]])
    if kind == KIND_ELLIPSOID:  # a Fibonacci lattice on the unit sphere
        k = np.arange(96) + 0.5
        z = 1 - 2 * k / 96
        phi = np.pi * (1 + 5**0.5) * k
        r = np.sqrt(1 - z * z)
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    raise ValueError(f"unknown primitive kind {kind}; expected one of box, ellipsoid, cylinder, cone (0-3)")


class GroundShadowMap:
    """Which ground points around one camera pose the sun cannot reach, softly.

    Args:
        prims: the primitives of the moment (all of them may cast a shadow).
        sun: unit vector toward the sun (world axes, z up); its z must be at least MIN_SUN_HEIGHT.
        camera_xy: the camera's world position; the map is centred on it...
        heading: ...and turned with it (radians).
    """

    def __init__(self, prims: PrimSet, sun: np.ndarray, camera_xy: tuple[float, float], heading: float):
        if sun[2] < MIN_SUN_HEIGHT:
            raise ValueError(
                f"the sun must stand at least {MIN_SUN_HEIGHT} high (unit z) to cast shadows, got {sun[2]}"
            )
        self.sun = np.asarray(sun, float)
        self.origin = np.asarray(camera_xy, float)
        c, s = np.cos(heading), np.sin(heading)
        self.to_ego = np.array([[c, s], [-s, c]])  # world xy offset -> (ahead, left)
        occluded = np.zeros((MAP_ROWS, MAP_COLS), np.uint8)  # anti-aliased: a sharp edge a cell wide
        distance = np.zeros((MAP_ROWS // COARSE, MAP_COLS // COARSE), np.float32)  # ground to occluder, m
        coarse_shift = _SUBPIXEL_BITS + int(np.log2(COARSE))
        for cells, metres in sorted(self._shadow_polygons(prims), key=lambda p: -p[1]):  # the nearest one wins
            cv2.fillConvexPoly(occluded, cells, 255, cv2.LINE_AA, _SUBPIXEL_BITS)
            cv2.fillConvexPoly(distance, cells, metres, cv2.LINE_8, coarse_shift)
        self.sharp = occluded.astype(np.float32) / 255
        coarse = cv2.resize(self.sharp, distance.shape[::-1], interpolation=cv2.INTER_AREA)
        soft = cv2.GaussianBlur(coarse, (0, 0), PENUMBRA_FAR_SIGMA_M / (MAP_CELL_M * COARSE))
        reach = 2 * int(np.ceil(3 * PENUMBRA_FAR_SIGMA_M / (MAP_CELL_M * COARSE))) + 1  # the soft edge lies outside
        self.soft_and_distance = np.dstack([soft, cv2.dilate(distance, np.ones((reach, reach), np.uint8))])

    def _cells(self, xy: np.ndarray) -> np.ndarray:
        """World ground positions (..., 2) -> fractional map (column, row)."""
        ego = (xy - self.origin) @ self.to_ego.T
        col = (ego[..., 0] - MAP_AHEAD_M[0]) / MAP_CELL_M - 0.5
        row = (MAP_SIDE_M - ego[..., 1]) / MAP_CELL_M - 0.5
        return np.stack([col, row], axis=-1)

    def _shadow_polygons(self, prims: PrimSet) -> list[tuple[np.ndarray, float]]:
        """Each primitive's shadow on the ground as (fixed-point hull cells, occluder distance in m)."""
        polygons = []
        for kind in (KIND_BOX, KIND_ELLIPSOID, KIND_CYLINDER, KIND_CONE):
            sel = np.flatnonzero(prims.kind == kind)
            if len(sel) == 0:
                continue
            outline = unit_outline(kind)[None] * prims.half[sel, None, :]  # (P, S, 3)
            points = prims.center[sel, None, :] + np.einsum("pij,psj->psi", prims.rot[sel], outline)
            ground = points[..., :2] - (np.maximum(points[..., 2], 0.0) / self.sun[2])[..., None] * self.sun[:2]
            cells = self._cells(ground)  # (P, S, 2)
            inside = (
                (cells[..., 0].max(1) >= 0)
                & (cells[..., 0].min(1) < MAP_COLS)
                & (cells[..., 1].max(1) >= 0)
                & (cells[..., 1].min(1) < MAP_ROWS)
            )
            metres = prims.center[sel, 2] / self.sun[2]
            for p in np.flatnonzero(inside):
                fixed = np.round(cells[p] * (1 << _SUBPIXEL_BITS)).astype(np.int32)
                polygons.append((cv2.convexHull(fixed), float(metres[p])))
        return polygons

    def at(self, points: np.ndarray) -> np.ndarray:
        """(N,) shadow in [0, 1] (1: the sun is hidden) at world points (N, 3) on the ground or the
        sidewalk; 0 outside the map, fading to 0 over its far end."""
        lifted = points[:, :2] - (points[:, 2] / self.sun[2])[:, None] * self.sun[:2]  # same sun ray, at z = 0
        cells = self._cells(lifted).astype(np.float32)
        sharp = _sample(self.sharp, cells)
        soft, distance = _sample(self.soft_and_distance, (cells + 0.5) / COARSE - 0.5).T
        weight = np.clip(distance / PENUMBRA_FAR_M, 0.0, 1.0)
        shadow = sharp * (1 - weight) + soft * weight
        ahead = (points[:, :2] - self.origin) @ self.to_ego[0]
        fade = np.clip((MAP_AHEAD_M[1] - ahead) / (MAP_AHEAD_M[1] - FADE_FROM_M), 0.0, 1.0)
        return shadow * fade


def _sample(image: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Bilinear samples of a float32 raster (rows, cols[, channels]) at fractional (column, row)
    cells (N, 2): (N[, channels]), 0 outside."""
    count = len(cells)
    rows = max(-(-count // 512), 1)
    maps = np.full((2, rows * 512), -2.0, np.float32)  # cv2.remap wants 2-D maps under 32767 rows
    maps[:, :count] = cells.T
    out = cv2.remap(
        image, maps[0].reshape(rows, 512), maps[1].reshape(rows, 512), cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT, borderValue=0.0,
    )  # fmt: skip
    return out.reshape(rows * 512, *image.shape[2:])[:count].astype(np.float64)
