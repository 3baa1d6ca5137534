"""Vectorised ray casting against the ground and the world's primitives.

Rays form a grid (camera pixels, or lidar channels x azimuth bins). Each primitive is tested only
against the rays inside a conservative rectangle of that grid (its projected bounding box), and
all (ray, primitive) pairs of one primitive kind are intersected in a single numpy pass. Ray
parameters t are in units of the direction vectors given: camera directions have a forward
component of 1, so t is the planar depth; lidar directions are unit vectors, so t is the range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from umad_common.datasets.synthetic.world import (
    CURB_HEIGHT,
    KIND_BOX,
    KIND_CONE,
    KIND_CYLINDER,
    KIND_ELLIPSOID,
    ROAD_HALF_WIDTH,
    SIDEWALK_OUTER,
    PrimSet,
    RoadCurve,
)

EPS = 1e-6
GROUND_ROAD, GROUND_SIDEWALK, GROUND_TERRAIN = 0, 1, 2
BOX_EDGES = np.array([(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1])


@dataclass
class GroundHit:
    t: np.ndarray  # (N,) inf where the ray does not reach the ground
    surface: np.ndarray  # (N,) GROUND_* class
    s: np.ndarray  # road coordinates of the hit point
    d: np.ndarray


def intersect_ground(origin: np.ndarray, dirs: np.ndarray, road: RoadCurve) -> GroundHit:
    """Flat ground z = 0 with the sidewalk strip raised to CURB_HEIGHT."""
    dz = dirs[:, 2]
    down = dz < -EPS
    n = len(dirs)
    t = np.full(n, np.inf)
    surface = np.full(n, GROUND_TERRAIN, np.int64)
    s, d = np.zeros(n), np.zeros(n)
    idx = np.flatnonzero(down)
    dsub = dirs[idx]
    t_low = -origin[2] / dsub[:, 2]
    s_lo, d_lo = road.to_road(origin[0] + t_low * dsub[:, 0], origin[1] + t_low * dsub[:, 1])
    t[idx], s[idx], d[idx] = t_low, s_lo, d_lo
    # Rays from the road reach the sidewalk's top only where their ground hit lies beyond the curb.
    far = np.abs(d_lo) >= ROAD_HALF_WIDTH - 0.5
    fidx, dfar = idx[far], dsub[far]
    t_high = (CURB_HEIGHT - origin[2]) / dfar[:, 2]
    s_hi, d_hi = road.to_road(origin[0] + t_high * dfar[:, 0], origin[1] + t_high * dfar[:, 1])
    on_walk = (np.abs(d_hi) >= ROAD_HALF_WIDTH) & (np.abs(d_hi) < SIDEWALK_OUTER)
    t[fidx[on_walk]], s[fidx[on_walk]], d[fidx[on_walk]] = t_high[on_walk], s_hi[on_walk], d_hi[on_walk]
    walk_lo = (np.abs(d_lo) >= ROAD_HALF_WIDTH) & (np.abs(d_lo) < SIDEWALK_OUTER)  # includes the curb's face
    surface[idx] = np.where(np.abs(d_lo) < ROAD_HALF_WIDTH, GROUND_ROAD, GROUND_TERRAIN)
    surface[idx[walk_lo]] = GROUND_SIDEWALK
    surface[fidx[on_walk]] = GROUND_SIDEWALK
    return GroundHit(t, surface, s, d)


def _intersect_unit(kind: int, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Nearest t > EPS where o + t d meets the unit primitive; inf on a miss. o, d: (n, 3)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        if kind == KIND_BOX:
            inv = 1.0 / d
            t1, t2 = (-1 - o) * inv, (1 - o) * inv
            t_near = np.nanmax(np.minimum(t1, t2), axis=1)
            t_far = np.nanmin(np.maximum(t1, t2), axis=1)
            t = np.where(t_near > EPS, t_near, t_far)
            return np.where((t_far >= t_near) & (t > EPS), t, np.inf)
        if kind == KIND_ELLIPSOID:
            a = np.einsum("ij,ij->i", d, d)
            b = np.einsum("ij,ij->i", o, d)
            c = np.einsum("ij,ij->i", o, o) - 1
            return _nearest_root(a, b, c)
        ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
        dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
        if kind == KIND_CYLINDER:
            a, b, c = dx * dx + dy * dy, ox * dx + oy * dy, ox * ox + oy * oy - 1
            radius_of = lambda z: np.ones_like(z)  # noqa: E731
        else:  # cone: x^2 + y^2 = ((1 - z) / 2)^2 for z in [-1, 1]
            kx = (1 - oz) / 2
            a = dx * dx + dy * dy - dz * dz / 4
            b = ox * dx + oy * dy + kx * dz / 2
            c = ox * ox + oy * oy - kx * kx
            radius_of = lambda z: (1 - z) / 2  # noqa: E731
        disc = b * b - a * c
        root = np.sqrt(np.maximum(disc, 0))
        best = np.full(len(o), np.inf)
        for t_side in ((-b - root) / a, (-b + root) / a):
            z = oz + t_side * dz
            ok = (disc >= 0) & (t_side > EPS) & (np.abs(z) <= 1) & (t_side < best)
            best = np.where(ok, t_side, best)
        caps = (1.0, -1.0) if kind == KIND_CYLINDER else (-1.0,)
        for zc in caps:
            t_cap = (zc - oz) / dz
            px, py = ox + t_cap * dx, oy + t_cap * dy
            ok = (t_cap > EPS) & (px * px + py * py <= radius_of(np.full_like(px, zc)) ** 2) & (t_cap < best)
            best = np.where(ok, t_cap, best)
        return best


def _nearest_root(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Smallest positive root of a t^2 + 2 b t + c = 0, inf if none."""
    disc = b * b - a * c
    root = np.sqrt(np.maximum(disc, 0))
    t1, t2 = (-b - root) / a, (-b + root) / a
    t = np.where(t1 > EPS, t1, t2)
    return np.where((disc >= 0) & (t > EPS), t, np.inf)


def unit_normal(kind: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Outward normals in unit-primitive space at hit points p (n, 3)."""
    n = np.zeros_like(p)
    box = kind == KIND_BOX
    if box.any():
        axis = np.argmax(np.abs(p[box]), axis=1)
        nb = np.zeros((int(box.sum()), 3))
        nb[np.arange(len(axis)), axis] = np.sign(p[box][np.arange(len(axis)), axis])
        n[box] = nb
    ell = kind == KIND_ELLIPSOID
    n[ell] = p[ell]
    for k in (KIND_CYLINDER, KIND_CONE):
        sel = kind == k
        if not sel.any():
            continue
        q = p[sel].copy()
        cap = np.abs(q[:, 2]) > 1 - 1e-4
        side = q.copy()
        if k == KIND_CYLINDER:
            side[:, 2] = 0.0
        else:  # gradient of x^2 + y^2 - (1 - z)^2 / 4
            side[:, :2] *= 2
            side[:, 2] = (1 - q[:, 2]) / 2
        side[cap] = 0.0
        side[cap, 2] = np.sign(q[cap, 2])
        n[sel] = side
    return n


@dataclass
class PrimHit:
    t: np.ndarray  # (N,) nearest primitive hit, inf where none
    prim: np.ndarray  # (N,) index of that primitive, -1 where none


def intersect_prims(
    origin: np.ndarray, dirs: np.ndarray, grid_shape: tuple[int, int], prims: PrimSet, rects: np.ndarray
) -> PrimHit:
    """Nearest primitive per ray; each primitive tested only inside its rectangle [r0, r1) x [c0, c1).

    Args:
        dirs: (R*C, 3) ray directions in row-major grid order.
        rects: (P, 4) int rectangles (r0, r1, c0, c1) in the grid; empty ones are skipped.
    """
    n_rays = len(dirs)
    t_best = np.full(n_rays, np.inf)
    prim_best = np.full(n_rays, -1, np.int64)
    heights, widths = rects[:, 1] - rects[:, 0], rects[:, 3] - rects[:, 2]
    active = np.flatnonzero((heights > 0) & (widths > 0))
    if len(active) == 0:
        return PrimHit(t_best, prim_best)
    m_all = prims.world_to_unit()
    o_local = np.einsum("pij,pj->pi", m_all, origin[None] - prims.center)
    pair_t, pair_ray, pair_prim = [], [], []
    for kind in (KIND_BOX, KIND_ELLIPSOID, KIND_CYLINDER, KIND_CONE):
        sel = active[prims.kind[active] == kind]
        if len(sel) == 0:
            continue
        counts = heights[sel] * widths[sel]
        owner = np.repeat(sel, counts)
        k = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        w = widths[owner]
        ray = (rects[owner, 0] + k // w) * grid_shape[1] + rects[owner, 2] + k % w
        d_local = np.einsum("nij,nj->ni", m_all[owner], dirs[ray])
        t = _intersect_unit(kind, o_local[owner], d_local)
        hit = np.isfinite(t)
        pair_t.append(t[hit])
        pair_ray.append(ray[hit])
        pair_prim.append(owner[hit])
    if not pair_t:
        return PrimHit(t_best, prim_best)
    t, ray, prim = np.concatenate(pair_t), np.concatenate(pair_ray), np.concatenate(pair_prim)
    np.minimum.at(t_best, ray, t)
    win = t == t_best[ray]
    prim_best[ray[win]] = prim[win]
    return PrimHit(t_best, prim_best)


def camera_rects(corners_cam: np.ndarray, focal: float, width: int, height: int, near: float = 0.05) -> np.ndarray:
    """Conservative pixel rectangles of boxes given by corners in camera axes (x right, y down, z forward).

    Edges crossing the near plane are clipped, so boxes beside or around the camera stay correct.
    """
    a = corners_cam[:, BOX_EDGES[:, 0]]
    b = corners_cam[:, BOX_EDGES[:, 1]]
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = (near - a[..., 2]) / (b[..., 2] - a[..., 2])
    crosses = (a[..., 2] - near) * (b[..., 2] - near) < 0
    clipped = a + np.where(crosses, frac, 0.0)[..., None] * (b - a)
    pts = np.concatenate([corners_cam, clipped], axis=1)
    valid = np.concatenate([corners_cam[..., 2] >= near, crosses], axis=1)
    z = np.where(valid, np.maximum(pts[..., 2], near), 1.0)
    u = focal * pts[..., 0] / z + width / 2
    v = focal * pts[..., 1] / z + height / 2
    big = 1e9
    u_lo, u_hi = np.where(valid, u, big).min(1), np.where(valid, u, -big).max(1)
    v_lo, v_hi = np.where(valid, v, big).min(1), np.where(valid, v, -big).max(1)
    rects = np.stack([np.floor(v_lo) - 1, np.floor(v_hi) + 2, np.floor(u_lo) - 1, np.floor(u_hi) + 2], axis=1)
    rects = np.clip(
        np.nan_to_num(rects, nan=0.0, posinf=big, neginf=-big), [0, 0, 0, 0], [height, height, width, width]
    )
    rects[~valid.any(1)] = 0
    return rects.astype(np.int64)


def spherical_rects(corners: np.ndarray, elevations: np.ndarray, n_azimuth: int, max_range: float) -> np.ndarray:
    """Conservative (channel, azimuth-bin) rectangles for a spinning lidar at the origin.

    Args:
        corners: (P, 8, 3) box corners in the sensor frame (x forward, y left, z up).
        elevations: (R,) channel elevations in radians, descending.
    """
    centre = corners.mean(1)
    rho_c = np.hypot(centre[:, 0], centre[:, 1])
    radius = np.max(np.hypot(corners[..., 0] - centre[:, None, 0], corners[..., 1] - centre[:, None, 1]), axis=1)
    az_c = np.arctan2(centre[:, 1], centre[:, 0])
    daz = np.angle(np.exp(1j * (np.arctan2(corners[..., 1], corners[..., 0]) - az_c[:, None])))
    az_lo, az_hi = az_c + daz.min(1), az_c + daz.max(1)
    step = 2 * np.pi / n_azimuth
    c_lo = np.floor((az_lo + np.pi) / step - 0.5) - 1
    c_hi = np.floor((az_hi + np.pi) / step - 0.5) + 3
    full = (rho_c < radius + 0.5) | (c_lo < 0) | (c_hi > n_azimuth)
    c_lo, c_hi = np.where(full, 0, c_lo), np.where(full, n_azimuth, c_hi)
    rho_min = np.maximum(rho_c - radius, 0.1)
    rho_max = rho_c + radius
    z_hi, z_lo = corners[..., 2].max(1), corners[..., 2].min(1)
    el_hi = np.maximum(np.arctan2(z_hi, rho_min), np.arctan2(z_hi, rho_max))
    el_lo = np.minimum(np.arctan2(z_lo, rho_min), np.arctan2(z_lo, rho_max))
    step_el = (elevations[0] - elevations[-1]) / (len(elevations) - 1)
    r_lo = np.floor((elevations[0] - el_hi) / step_el) - 1
    r_hi = np.floor((elevations[0] - el_lo) / step_el) + 2
    rects = np.stack([r_lo, r_hi, c_lo, c_hi], axis=1)
    rects = np.clip(rects, 0, [len(elevations), len(elevations), n_azimuth, n_azimuth])
    rects[rho_min > max_range] = 0
    return rects.astype(np.int64)
