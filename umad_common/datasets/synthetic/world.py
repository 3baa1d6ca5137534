"""The synthetic world's static geometry: a curving two-lane road and the primitives placed along it.

Frame conventions (right-handed, metres): world x forward along the road's general direction,
y to the left, z up. The road centreline is the curve y = f(x), a sum of sinusoids; positions
along it are given in road coordinates (s = arc length, d = signed lateral offset, left positive).
Everything that is not the ground is a primitive (box, ellipsoid, cylinder, cone) with a pose
and half extents, a CARLA semantic tag, an instance id and a material.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

LANE_WIDTH = 3.5  # each of the two lanes; the centre line is d = 0
ROAD_HALF_WIDTH = 5.5  # lanes plus a 2 m parking strip on each side
SIDEWALK_OUTER = 8.5  # sidewalk from the curb (|d| = 5.5) to here, raised by CURB_HEIGHT
CURB_HEIGHT = 0.15
PARKING_OFFSET = 4.5  # |d| of parked cars' centres
POLE_ROW_D = 5.9  # |d| of the bare poles' row (the facades stress set): on the sidewalk just past the curb
EGO_LANE_D = -LANE_WIDTH / 2  # right-hand traffic: the ego lane is right of the centre line
ONCOMING_LANE_D = LANE_WIDTH / 2

# CARLA 0.9.14 semantic tags used by the world.
TAG_ROAD, TAG_SIDEWALK, TAG_BUILDING, TAG_POLE, TAG_SIGN = 1, 2, 3, 6, 8
TAG_VEGETATION, TAG_TERRAIN, TAG_SKY, TAG_CAR, TAG_ROAD_LINE = 9, 10, 11, 14, 24

KIND_BOX, KIND_ELLIPSOID, KIND_CYLINDER, KIND_CONE = 0, 1, 2, 3
MAT_PLAIN, MAT_WINDOWS, MAT_FOLIAGE, MAT_STRIPES, MAT_ROUGH, MAT_SPOTS, MAT_GLASS, MAT_LAMP = range(8)

BUILDING_COLOURS = [(0.70, 0.62, 0.50), (0.55, 0.32, 0.24), (0.50, 0.50, 0.52), (0.80, 0.76, 0.66), (0.42, 0.46, 0.52)]
CAR_COLOURS = [
    (0.82, 0.82, 0.80),
    (0.08, 0.08, 0.09),
    (0.58, 0.59, 0.60),
    (0.42, 0.08, 0.08),
    (0.10, 0.15, 0.38),
    (0.30, 0.34, 0.30),
]
FOLIAGE_COLOURS = [(0.22, 0.36, 0.12), (0.28, 0.40, 0.16), (0.18, 0.30, 0.14)]


class RoadCurve:
    """Centreline y = f(x) with a lookup table from x to arc length s (and back)."""

    def __init__(self, rng: np.random.Generator, x_end: float, max_curvature: float = 1 / 70):
        n = 3
        wavelengths = np.array([rng.uniform(260, 520), rng.uniform(120, 220), rng.uniform(60, 110)])
        self.freq = 2 * np.pi / wavelengths
        self.amp = np.array([rng.uniform(0, 45), rng.uniform(0, 12), rng.uniform(0, 2.0)]) * rng.choice([-1, 1], n)
        self.phase = rng.uniform(0, 2 * np.pi, n)
        peak = float(np.sum(np.abs(self.amp) * self.freq**2))  # upper bound of |f''| >= |curvature|
        if peak > max_curvature:
            self.amp *= max_curvature / peak
        self.x_table = np.arange(-200.0, x_end + 200.0, 0.25)
        ds = np.sqrt(1 + self.slope(self.x_table) ** 2) * 0.25
        s = np.concatenate([[0.0], np.cumsum(0.5 * (ds[1:] + ds[:-1]))])
        self.s_table = s - np.interp(0.0, self.x_table, s)  # s = 0 at x = 0

    def y(self, x: np.ndarray) -> np.ndarray:
        return np.einsum("...k,k->...", np.sin(np.multiply.outer(x, self.freq) + self.phase), self.amp)

    def slope(self, x: np.ndarray) -> np.ndarray:
        return np.einsum("...k,k->...", np.cos(np.multiply.outer(x, self.freq) + self.phase), self.amp * self.freq)

    def second(self, x: np.ndarray) -> np.ndarray:
        return -np.einsum("...k,k->...", np.sin(np.multiply.outer(x, self.freq) + self.phase), self.amp * self.freq**2)

    def x_at(self, s: np.ndarray) -> np.ndarray:
        return np.interp(s, self.s_table, self.x_table)

    def curvature(self, s: np.ndarray) -> np.ndarray:
        """Signed curvature of the centreline (positive = turning left) at arc length s."""
        x = self.x_at(s)
        return self.second(x) / (1 + self.slope(x) ** 2) ** 1.5

    def to_world(self, s: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Road coordinates -> world (x, y, heading in radians)."""
        x = self.x_at(s)
        fp = self.slope(x)
        norm = np.sqrt(1 + fp**2)
        return x - d * fp / norm, self.y(x) + d / norm, np.arctan(fp)

    def to_road(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World -> road coordinates, first order in the offset (exact on straights, cm-accurate on
        the gentle curves used here)."""
        fp = self.slope(x)
        norm = np.sqrt(1 + fp**2)
        off = y - self.y(x)
        return np.interp(x, self.x_table, self.s_table) + off * fp / norm, off / norm


@dataclass
class Part:
    """One primitive of an object, in the object's frame (x forward, origin on the ground)."""

    kind: int
    center: tuple[float, float, float]
    half: tuple[float, float, float]
    tag: int
    colour: tuple[float, float, float]
    material: int = MAT_PLAIN
    yaw: float = 0.0
    pitch: float = 0.0  # rotation about the part's y axis (lays a cylinder down)


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@dataclass
class PrimSet:
    """Primitives as parallel arrays. `rot` maps the primitive's axes to world; the primitive is the
    unit cube/sphere/cylinder/cone scaled by `half`."""

    kind: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    center: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    half: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    rot: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    tag: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    inst: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    colour: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    material: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __len__(self) -> int:
        return len(self.kind)

    @staticmethod
    def from_parts(parts: list[Part], x: float, y: float, yaw: float, inst: int, z: float = 0.0) -> PrimSet:
        """Place an object's parts at world (x, y, z) with heading `yaw`."""
        r_obj = rot_z(yaw)
        rots = [r_obj @ rot_z(p.yaw) @ rot_y(p.pitch) for p in parts]
        centers = [np.array([x, y, z]) + r_obj @ np.asarray(p.center, float) for p in parts]
        return PrimSet(
            kind=np.array([p.kind for p in parts], np.int64),
            center=np.array(centers, float),
            half=np.array([p.half for p in parts], float),
            rot=np.array(rots, float),
            tag=np.array([p.tag for p in parts], np.int64),
            inst=np.full(len(parts), inst, np.int64),
            colour=np.array([p.colour for p in parts], float),
            material=np.array([p.material for p in parts], np.int64),
        )

    @staticmethod
    def concat(sets: list[PrimSet]) -> PrimSet:
        sets = [s for s in sets if len(s)] or [PrimSet()]
        return PrimSet(*(np.concatenate([getattr(s, f) for s in sets]) for f in PrimSet.__dataclass_fields__))

    def world_to_unit(self) -> np.ndarray:
        """(P, 3, 3) matrices taking world offsets from the centre into unit-primitive space."""
        return np.transpose(self.rot, (0, 2, 1)) / self.half[:, :, None]

    def corners(self) -> np.ndarray:
        """(P, 8, 3) world corners of each primitive's bounding box."""
        signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
        local = signs[None] * self.half[:, None, :]
        return self.center[:, None, :] + np.einsum("pij,pkj->pki", self.rot, local)


def car_parts(rng: np.random.Generator) -> list[Part]:
    """A car of random size and paint: body, glass cabin, four wheels."""
    length, width = rng.uniform(4.0, 4.8), rng.uniform(1.75, 1.95)
    paint = CAR_COLOURS[rng.integers(len(CAR_COLOURS))]
    body_top, cabin_top = rng.uniform(0.95, 1.1), rng.uniform(1.4, 1.6)
    cabin_len = length * rng.uniform(0.45, 0.55)
    wheel = (0.08, 0.08, 0.08)
    parts = [
        Part(KIND_BOX, (0, 0, (0.3 + body_top) / 2), (length / 2, width / 2, (body_top - 0.3) / 2), TAG_CAR, paint),
        Part(
            KIND_BOX,
            (-0.1 * length, 0, (body_top + cabin_top) / 2),
            (cabin_len / 2, width / 2 - 0.08, (cabin_top - body_top) / 2),
            TAG_CAR,
            paint,
            MAT_GLASS,
        ),
    ]
    for sx in (-1, 1):
        for sy in (-1, 1):
            center = (sx * (length / 2 - 0.8), sy * (width / 2 - 0.12), 0.34)
            parts.append(
                Part(KIND_CYLINDER, center, (0.34, 0.34, 0.12), TAG_CAR, wheel, yaw=np.pi / 2, pitch=np.pi / 2)
            )
    return parts


def tree_parts(rng: np.random.Generator) -> list[Part]:
    """A broadleaf tree: trunk and one or two foliage ellipsoids."""
    trunk_h = rng.uniform(1.8, 3.2)
    crown_r = rng.uniform(1.4, 2.8)
    green = FOLIAGE_COLOURS[rng.integers(len(FOLIAGE_COLOURS))]
    parts = [
        Part(
            KIND_CYLINDER, (0, 0, trunk_h / 2), (0.18, 0.18, trunk_h / 2), TAG_VEGETATION, (0.30, 0.22, 0.15), MAT_ROUGH
        ),
        Part(
            KIND_ELLIPSOID,
            (0, 0, trunk_h + crown_r * 0.8),
            (crown_r, crown_r, crown_r * 1.1),
            TAG_VEGETATION,
            green,
            MAT_FOLIAGE,
        ),
    ]
    if rng.random() < 0.5:
        off = rng.uniform(-0.6, 0.6, 2) * crown_r
        parts.append(
            Part(
                KIND_ELLIPSOID,
                (off[0], off[1], trunk_h + crown_r * 1.5),
                (crown_r * 0.7,) * 3,
                TAG_VEGETATION,
                green,
                MAT_FOLIAGE,
            )
        )
    return parts


def lamp_parts(side: int) -> list[Part]:
    """A street lamp on the sidewalk whose arm reaches over the road (side = +1 left, -1 right)."""
    grey = (0.32, 0.33, 0.35)
    return [
        Part(KIND_CYLINDER, (0, 0, 3.75), (0.09, 0.09, 3.75), TAG_POLE, grey),
        Part(KIND_BOX, (0, -side * 0.9, 7.45), (0.06, 0.9, 0.05), TAG_POLE, grey),
        Part(KIND_BOX, (0, -side * 1.7, 7.35), (0.2, 0.28, 0.08), TAG_POLE, (0.75, 0.75, 0.7), MAT_LAMP),
    ]


def sign_parts(rng: np.random.Generator) -> list[Part]:
    """A traffic sign: a thin pole with a plate facing the road."""
    plate = [(0.12, 0.25, 0.62), (0.92, 0.92, 0.92), (0.10, 0.40, 0.15)][rng.integers(3)]
    return [
        Part(KIND_CYLINDER, (0, 0, 1.25), (0.05, 0.05, 1.25), TAG_POLE, (0.5, 0.5, 0.52)),
        Part(KIND_BOX, (0, 0, 2.7), (0.03, 0.4, 0.35), TAG_SIGN, plate),
    ]


def pole_parts(rng: np.random.Generator) -> list[Part]:
    """A bare thin pole (a bollard-like post or a pole without its sign), 2.5-4.5 m tall."""
    height, radius = rng.uniform(2.5, 4.5), rng.uniform(0.05, 0.08)
    grey = (0.36, 0.37, 0.39) if rng.random() < 0.5 else (0.55, 0.55, 0.57)
    return [Part(KIND_CYLINDER, (0, 0, height / 2), (radius, radius, height / 2), TAG_POLE, grey)]


@dataclass
class WorldStyle:
    """How built-up the surroundings are (probabilities per slot along the road)."""

    name: str
    building: float
    tree: float
    parked_car: float
    far_trees: int  # trees scattered on open terrain per 100 m


STYLES = [
    WorldStyle("urban", 0.92, 0.35, 0.55, 0),
    WorldStyle("suburban", 0.55, 0.7, 0.35, 4),
    WorldStyle("rural", 0.12, 0.8, 0.12, 14),
]


def build_static_world(
    rng: np.random.Generator,
    road: RoadCurve,
    s_range: tuple[float, float],
    style: WorldStyle,
    keep_clear: list[tuple[float, float]],
    pole_spacing: tuple[float, float] | None = None,
) -> tuple[PrimSet, int]:
    """Buildings, trees, lamps, signs and parked cars along the road.

    Args:
        keep_clear: (s, d) points on the road where nothing may be parked within 8 m (anomalies).
        pole_spacing: (least, most) metres between the bare thin poles of a row on each sidewalk at
            |d| = POLE_ROW_D, drawn after everything else (the facades stress set); None: no such
            row, and the world is drawn exactly as before.

    Returns:
        The primitives and the next unused instance id.
    """
    sets: list[PrimSet] = []
    inst = 1

    def place(parts: list[Part], s: float, d: float, extra_yaw: float = 0.0) -> None:
        nonlocal inst
        x, y, heading = road.to_world(np.array(s), np.array(d))
        sets.append(PrimSet.from_parts(parts, float(x), float(y), float(heading) + extra_yaw, inst))
        inst += 1

    s0, s1 = s_range
    lamps: dict[int, list[float]] = {-1: [], 1: []}
    for side in (-1, 1):
        s = s0 + rng.uniform(0, 10)
        while s < s1:  # building lots
            length, gap = rng.uniform(8, 22), rng.uniform(1.5, 8)
            if rng.random() < style.building:
                depth, height = rng.uniform(8, 16), rng.uniform(5, 24)
                setback = rng.uniform(10.5, 13.0)
                colour = np.array(BUILDING_COLOURS[rng.integers(len(BUILDING_COLOURS))]) * rng.uniform(0.85, 1.1)
                part = Part(
                    KIND_BOX,
                    (0, 0, height / 2),
                    (length / 2, depth / 2, height / 2),
                    TAG_BUILDING,
                    tuple(colour),
                    MAT_WINDOWS,
                )
                place([part], s + length / 2, side * (setback + depth / 2))
            s += length + gap
        s = s0 + rng.uniform(0, 8)
        while s < s1:  # trees between sidewalk and lots
            if rng.random() < style.tree:
                place(tree_parts(rng), s, side * rng.uniform(9.0, 10.0))
            s += rng.uniform(7, 14)
        for _ in range(int(style.far_trees * (s1 - s0) / 100)):
            place(tree_parts(rng), rng.uniform(s0, s1), side * rng.uniform(12, 45))
        s = s0 + rng.uniform(0, 30) + (15 if side > 0 else 0)
        while s < s1:  # lamps
            place(lamp_parts(side), s, side * 6.0)
            lamps[side].append(s)
            s += rng.uniform(26, 36)
        s = s0 + rng.uniform(0, 40)
        while s < s1:  # signs
            place(sign_parts(rng), s, side * 6.6, extra_yaw=0.0)
            s += rng.uniform(60, 140)
        s = s0 + rng.uniform(0, 6)
        while s < s1:  # parked cars
            if rng.random() < style.parked_car and all(
                abs(s - ks) > 8 or abs(side * PARKING_OFFSET - kd) > 3 for ks, kd in keep_clear
            ):
                place(
                    car_parts(rng),
                    s,
                    side * PARKING_OFFSET + rng.uniform(-0.15, 0.15),
                    extra_yaw=np.pi if side > 0 else 0.0,
                )
                s += rng.uniform(5.5, 8)
            else:
                s += rng.uniform(6, 18)
    if pole_spacing is not None:
        for side in (-1, 1):
            s = s0 + rng.uniform(0, pole_spacing[1])
            while s < s1:  # bare poles, none where a lamp's pole stands
                if all(abs(s - lamp_s) > 1.0 for lamp_s in lamps[side]):
                    place(pole_parts(rng), s, side * (POLE_ROW_D + rng.uniform(-0.1, 0.1)))
                s += rng.uniform(*pole_spacing)
    return PrimSet.concat(sets), inst
