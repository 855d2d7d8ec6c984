"""Stage 3: ray casting detections onto the road surface and multi-frame fusion (SPEC §3)."""

from pavemap.detect.filter import filter_detections
from pavemap.fuse.config import FusionConfig
from pavemap.fuse.core import FusionResult, associate_detections, fuse, instances_to_features, write_fusion

__all__ = ["FusionConfig", "FusionResult", "associate_detections", "filter_detections", "fuse", "instances_to_features",
           "write_fusion"]
