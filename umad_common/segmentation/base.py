"""What every segmenter method shares: the `SegmenterMethod` base class and label-map helpers.

A method is a class with a `name`, its own small pydantic `Params`, the input ports it needs beyond
the image, and one function from a (h, w, 3) float32 image in [0, 1] (plus the frame's other
inputs) to (K, h, w) bool masks (K may be 0). `operators/segmenter.py` is a thin per-frame adapter
around one method; `umad bench segmenters` measures every registered method the same way.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict
from skimage.measure import label as label_regions

from umad_common.dataflow import Context, Frame

TUNED = "chosen on validation seed 2 (best refined AP) by `umad bench segmenters --tune`"  # provenance


def sklearn_cluster() -> Any:
    """scikit-learn's clustering module, imported when a method that clusters is built, not with this
    package: every replica of a graph loads every operator class to check the wiring, and this import
    was a large part of each replica's start-up CPU (docs/experiments.md)."""
    import sklearn.cluster

    return sklearn.cluster


class NoOptions(BaseModel):
    """Parameters of a method that takes none."""

    model_config = ConfigDict(extra="forbid")


class SegmenterMethod:
    """Base class of every segmenter method (built-in or a user's `package.module:Class`).

    Class attributes:
        name: the registry name graph.yaml's `method` uses.
        Params: the method's parameters (pydantic, `extra="forbid"`, every field with a default and
            a description; a default chosen with labels says so, naming the validation seed).
        needs: input ports of the segmenter operator the method reads besides `frame`
            (`truth`, `lidar`); `umad graph check` refuses a graph that leaves one unwired.
        tuning_grid: `{option: [values]}` that `umad bench segmenters --tune` measures.
    """

    name: ClassVar[str] = ""
    Params: ClassVar[type[BaseModel]] = NoOptions
    needs: ClassVar[tuple[str, ...]] = ()
    tuning_grid: ClassVar[dict[str, list[Any]]] = {}

    def __init__(self, params: BaseModel, context: Context):
        """Load everything the method needs (weight files fail here, not at the first frame)."""
        self.params = params
        self.context = context

    @classmethod
    def from_options(cls, options: BaseModel | dict[str, Any], context: Context | None = None) -> SegmenterMethod:
        """Validate `options` against `Params` (pydantic.ValidationError names the field) and construct."""
        params = options if isinstance(options, cls.Params) else cls.Params.model_validate(dict(options))
        return cls(params, context or Context())

    @classmethod
    def required_inputs(cls, params: BaseModel) -> set[str]:
        """The input ports these parameters need (a combination adds its parts' needs)."""
        return set(cls.needs)

    def __call__(self, image: np.ndarray, frame: Frame) -> np.ndarray:
        """(K, h, w) bool masks of `image` (h, w, 3) float32 in [0, 1]; `frame` holds the other inputs."""
        raise NotImplementedError


class SegmenterInputError(ValueError):
    """A frame's input cannot serve a method (a sensor setup without the camera, lidar points of the
    wrong shape); the message names the frame and what was expected."""


def labels_to_masks(labels: np.ndarray, min_area: int = 1, ignore: int | None = None) -> np.ndarray:
    """One bool mask per distinct label with at least `min_area` pixels, largest first.

    Args:
        labels: (h, w) integer label map.
        min_area: smaller regions get no mask (their pixels stay uncovered).
        ignore: a label value that gets no mask (e.g. 0 = "no instance").
    """
    ids, counts = np.unique(labels, return_counts=True)
    keep = counts >= min_area
    if ignore is not None:
        keep &= ids != ignore
    ids, counts = ids[keep], counts[keep]
    ids = ids[np.argsort(-counts, kind="stable")]
    return labels[None, :, :] == ids[:, None, None]


def connected_regions(labels: np.ndarray) -> np.ndarray:
    """Relabel so that each 4-connected region of equal label gets its own id (0..n-1); pixels
    labelled -1 stay -1."""
    return label_regions(labels, background=-1, connectivity=1) - 1


def masks_to_labels(masks: np.ndarray) -> np.ndarray:
    """(K, h, w) bool masks that tile (at most one mask per pixel) -> (h, w) int label map, -1 where
    no mask covers the pixel."""
    labels = np.full(masks.shape[1:], -1, np.int64)
    for k, mask in enumerate(masks):
        labels[mask] = k
    return labels
