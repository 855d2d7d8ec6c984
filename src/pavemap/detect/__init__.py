"""Stage 2: detections in (any backend or a user's file), its settings, and the semantic road filter."""

from pavemap.detect.boxes import box_ratio, integral_image
from pavemap.detect.config import DetectorConfig, FilterConfig
from pavemap.detect.filter import FilterResult, filter_detections, sanitize
from pavemap.detect.sources import load_detections, read_yolo_dir, read_yolo_txt

__all__ = [
    "DetectorConfig",
    "FilterConfig",
    "FilterResult",
    "box_ratio",
    "filter_detections",
    "integral_image",
    "load_detections",
    "read_yolo_dir",
    "read_yolo_txt",
    "sanitize",
]
