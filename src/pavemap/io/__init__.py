"""Reading and writing the sequence folder (SPEC §6) and importers of real data."""

from pavemap.io.atomic import atomic_path, atomic_write_json, atomic_write_text
from pavemap.io.sequence import (
    SequenceError,
    load_depth,
    load_rgb,
    load_semantics,
    read_detections,
    read_sequence,
    save_depth,
    validate_sequence,
    write_detections,
    write_sequence,
)

__all__ = [
    "SequenceError",
    "atomic_path",
    "atomic_write_json",
    "atomic_write_text",
    "load_depth",
    "load_rgb",
    "load_semantics",
    "read_detections",
    "read_sequence",
    "save_depth",
    "validate_sequence",
    "write_detections",
    "write_sequence",
]
