"""Stage 3: ray casting filtered detections onto the road surface and multi-frame fusion (SPEC §3).

Stage 3 takes stage 2's :class:`pavemap.detect.filter.FilterResult` as data; the two packages do
not import each other (``pavemap.pipeline`` calls the filter, then fusion).
"""

from pavemap.fuse.associate import ASSOCIATIONS, Association, associate_detections
from pavemap.fuse.config import FusionConfig
from pavemap.fuse.core import FusionResult, fuse

__all__ = ["ASSOCIATIONS", "Association", "FusionConfig", "FusionResult", "associate_detections", "fuse"]
