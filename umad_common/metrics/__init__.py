"""Evaluation metrics: exact streaming pixel metrics over float16 scores, SegmentMeIfYouCan component metrics."""

from umad_common.metrics.components import ComponentMetrics, component_metrics, frame_components
from umad_common.metrics.pixel import PixelMetrics

__all__ = ["ComponentMetrics", "PixelMetrics", "component_metrics", "frame_components"]
