"""Anomalous objects: static things on the road of the AnoVox categories, in shapes and colours that
no normal drive contains (normal scenes hold only buildings, trees, lamps, signs and muted cars)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from umad_common.datasets.synthetic.world import (
    KIND_BOX,
    KIND_CONE,
    KIND_CYLINDER,
    KIND_ELLIPSOID,
    MAT_PLAIN,
    MAT_ROUGH,
    MAT_SPOTS,
    MAT_STRIPES,
    Part,
)

TAG_HOME, TAG_ANIMAL, TAG_NATURE, TAG_SPECIAL = 29, 30, 31, 32
ANOMALY_TAGS = (29, 30, 31, 32, 33, 34, 100)

# Saturated colours that appear nowhere in normal drives.
VIVID = [
    (0.85, 0.10, 0.75),
    (0.50, 0.10, 0.72),
    (0.00, 0.72, 0.78),
    (1.00, 0.45, 0.00),
    (0.95, 0.85, 0.00),
    (1.00, 0.50, 0.75),
    (0.60, 0.95, 0.10),
]


@dataclass
class AnomalyShape:
    """An anomaly's parts (object frame, x forward) and what the ANOMALY csv says about it."""

    category: str
    tag: int
    type_id: str
    parts: list[Part]
    size: tuple[float, float, float]  # length, width, height (m)


def _vivid(rng: np.random.Generator) -> tuple[float, float, float]:
    return VIVID[rng.integers(len(VIVID))]


def home_object(rng: np.random.Generator) -> AnomalyShape:
    """Furniture: a sofa, a table or a wardrobe."""
    colour, t = _vivid(rng), TAG_HOME
    variant = ["sofa", "table", "wardrobe"][rng.integers(3)]
    if variant == "sofa":
        w = rng.uniform(1.6, 2.2)
        parts = [
            Part(KIND_BOX, (0, 0, 0.3), (0.45, w / 2, 0.2), t, colour),
            Part(KIND_BOX, (-0.35, 0, 0.75), (0.12, w / 2, 0.28), t, colour),
            Part(KIND_BOX, (0, w / 2 - 0.1, 0.6), (0.45, 0.1, 0.12), t, colour),
            Part(KIND_BOX, (0, -w / 2 + 0.1, 0.6), (0.45, 0.1, 0.12), t, colour),
        ]
        size = (0.9, w, 1.03)
    elif variant == "table":
        length, w = rng.uniform(1.2, 1.8), rng.uniform(0.8, 1.0)
        parts = [Part(KIND_BOX, (0, 0, 0.74), (length / 2, w / 2, 0.03), t, colour)]
        for sx in (-1, 1):
            for sy in (-1, 1):
                parts.append(
                    Part(
                        KIND_CYLINDER,
                        (sx * (length / 2 - 0.08), sy * (w / 2 - 0.08), 0.36),
                        (0.04, 0.04, 0.36),
                        t,
                        colour,
                    )
                )
        size = (length, w, 0.77)
    else:
        w, h = rng.uniform(0.9, 1.4), rng.uniform(1.6, 2.0)
        parts = [Part(KIND_BOX, (0, 0, h / 2), (0.3, w / 2, h / 2), t, colour, MAT_STRIPES)]
        size = (0.6, w, h)
    return AnomalyShape("home", t, f"synthetic.home.{variant}", parts, size)


def animal_object(rng: np.random.Generator) -> AnomalyShape:
    """A four-legged animal (deer, cow or dog sized) standing across or along the lane."""
    variant = ["deer", "cow", "dog"][rng.integers(3)]
    scale = {"deer": 1.0, "cow": 1.35, "dog": 0.5}[variant] * rng.uniform(0.9, 1.1)
    coat = {"deer": (0.55, 0.33, 0.16), "cow": (0.92, 0.9, 0.86), "dog": (0.85, 0.55, 0.25)}[variant]
    material = MAT_SPOTS if variant == "cow" else MAT_PLAIN
    t, leg = TAG_ANIMAL, 0.8 * scale
    body_z = leg + 0.25 * scale
    parts = [
        Part(KIND_ELLIPSOID, (0, 0, body_z), (0.65 * scale, 0.25 * scale, 0.3 * scale), t, coat, material),
        Part(
            KIND_CYLINDER,
            (0.6 * scale, 0, body_z + 0.3 * scale),
            (0.09 * scale, 0.09 * scale, 0.25 * scale),
            t,
            coat,
            pitch=0.5,
        ),
        Part(
            KIND_ELLIPSOID,
            (0.78 * scale, 0, body_z + 0.55 * scale),
            (0.22 * scale, 0.11 * scale, 0.12 * scale),
            t,
            coat,
            material,
        ),
    ]
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(
                Part(
                    KIND_CYLINDER,
                    (sx * 0.42 * scale, sy * 0.13 * scale, leg / 2 + 0.1 * scale),
                    (0.05 * scale, 0.05 * scale, leg / 2 + 0.1 * scale),
                    t,
                    coat,
                )
            )
    return AnomalyShape(
        "animal", t, f"synthetic.animal.{variant}", parts, (1.8 * scale, 0.6 * scale, body_z + 0.7 * scale)
    )


def nature_object(rng: np.random.Generator) -> AnomalyShape:
    """A boulder, a fallen trunk across the lane, or a bush in autumn colours."""
    variant = ["boulder", "log", "bush"][rng.integers(3)]
    t = TAG_NATURE
    if variant == "boulder":
        r = rng.uniform(0.5, 0.9)
        parts = [
            Part(KIND_ELLIPSOID, (0, 0, r * 0.6), (r, r * 0.85, r * 0.7), t, (0.47, 0.42, 0.38), MAT_ROUGH),
            Part(
                KIND_ELLIPSOID,
                (r * 0.6, r * 0.4, r * 0.35),
                (r * 0.5, r * 0.45, r * 0.4),
                t,
                (0.47, 0.42, 0.38),
                MAT_ROUGH,
            ),
        ]
        size = (2 * r, 1.7 * r, 1.3 * r)
    elif variant == "log":
        length, r = rng.uniform(2.5, 4.0), rng.uniform(0.2, 0.32)
        parts = [
            Part(
                KIND_CYLINDER,
                (0, 0, r),
                (r, r, length / 2),
                t,
                (0.42, 0.26, 0.12),
                MAT_ROUGH,
                yaw=np.pi / 2 + rng.uniform(-0.3, 0.3),
                pitch=np.pi / 2,
            )
        ]
        size = (2 * r, length, 2 * r)
    else:
        r = rng.uniform(0.6, 1.0)
        colour = [(0.85, 0.35, 0.05), (0.75, 0.12, 0.10), (0.90, 0.65, 0.05)][rng.integers(3)]
        parts = [Part(KIND_ELLIPSOID, (0, 0, r * 0.8), (r, r * 1.2, r * 0.8), t, colour, MAT_ROUGH)]
        size = (2 * r, 2.4 * r, 1.6 * r)
    return AnomalyShape("nature", t, f"synthetic.nature.{variant}", parts, size)


def special_object(rng: np.random.Generator) -> AnomalyShape:
    """Traffic cones, a striped barrel or a big ball."""
    variant = ["cones", "barrel", "ball"][rng.integers(3)]
    t = TAG_SPECIAL
    if variant == "cones":
        parts = []
        for k in range(3):
            y = (k - 1) * rng.uniform(0.7, 1.1)
            parts.append(
                Part(KIND_CONE, (rng.uniform(-0.3, 0.3), y, 0.4), (0.2, 0.2, 0.4), t, (1.0, 0.42, 0.0), MAT_STRIPES)
            )
            parts.append(Part(KIND_BOX, (parts[-1].center[0], y, 0.02), (0.24, 0.24, 0.02), t, (0.1, 0.1, 0.1)))
        size = (0.5, 2.5, 0.8)
    elif variant == "barrel":
        r, h = rng.uniform(0.28, 0.35), rng.uniform(0.9, 1.1)
        parts = [Part(KIND_CYLINDER, (0, 0, h / 2), (r, r, h / 2), t, (1.0, 0.40, 0.0), MAT_STRIPES)]
        size = (2 * r, 2 * r, h)
    else:
        r = rng.uniform(0.35, 0.7)
        parts = [Part(KIND_ELLIPSOID, (0, 0, r), (r, r, r), t, _vivid(rng), MAT_STRIPES)]
        size = (2 * r, 2 * r, 2 * r)
    return AnomalyShape("special", t, f"synthetic.special.{variant}", parts, size)


BUILDERS = {"home": home_object, "animal": animal_object, "nature": nature_object, "special": special_object}
CATEGORIES = tuple(BUILDERS)


def make_anomaly(rng: np.random.Generator, category: str) -> AnomalyShape:
    """Build a random object of one AnoVox category ("home", "animal", "nature", "special")."""
    if category not in BUILDERS:
        raise ValueError(f"unknown anomaly category {category!r}; expected one of {CATEGORIES}")
    return BUILDERS[category](rng)
