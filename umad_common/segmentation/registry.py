"""The segmenter methods by name, and the lookup of a method by name or `package.module:Class` path.

`SEGMENTERS` is filled by the package (`umad_common/segmentation/__init__.py` registers every
built-in method), which Python imports before any module in it; so a lookup from a method's own
module sees every method without importing them: `geometry`, whose `rest` may be any other method
(`learned` among them, itself a geometry), asks here.
"""

from __future__ import annotations

from umad_common.dataflow.api.plugins import registered_class
from umad_common.segmentation.base import SegmenterMethod

SEGMENTERS: dict[str, type[SegmenterMethod]] = {}  # name -> the built-in method's class


class UnknownSegmenterError(LookupError):
    """A method name that is neither registered nor a loadable `package.module:Class` path."""


def register(*classes: type[SegmenterMethod]) -> None:
    """Name built-in methods in `SEGMENTERS`, each by its `name`."""
    SEGMENTERS.update({cls.name: cls for cls in classes})


def segmenter_class(name: str) -> type[SegmenterMethod]:
    """The class for a registered name or a `package.module:ClassName` import path."""
    return registered_class(name, SEGMENTERS, SegmenterMethod, "segmenter method", UnknownSegmenterError)
